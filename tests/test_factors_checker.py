"""Static integrity: the AST whitelist admits the factor language and rejects hostile code by rule id."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from mira.factors import (
    RULES,
    CompiledProgram,
    Factor,
    FactorProgram,
    InadmissibleCodeError,
    check_code,
    check_program,
    compile_factor,
    example_program,
    example_programs,
)
from mira.factors.checker import check_metadata, parse_range_hint
from mira.tasks import load_task

FEATURES = ["torso_height", "pitch", "x_velocity", "z_velocity", "pitch_rate", "back_thigh_angle"]
MARKER = "/tmp/mira_factor_marker_should_not_exist"


def rules(code: str, kind: str = "PHI", name: str = "f") -> set[str]:
    return {v.rule for v in check_code(name, kind, code, FEATURES) if v.is_error}


def body(*lines: str, sig: str = "s") -> str:
    return f"def f({sig}):\n" + "".join(f"    {line}\n" for line in lines)


# ------------------------------------------------------------------ admitted


@pytest.mark.parametrize(
    "code,kind",
    [
        (body("return s.x_velocity"), "PHI"),
        (body('"""a docstring is fine"""', "return -1.0 * s.pitch ** 2"), "PHI"),
        (body("v = s.x_velocity", "g = 1.0 - np.tanh(2.0 * s.pitch ** 2)", "return v * g"), "PHI"),
        (body("x, y = s.x_velocity, s.z_velocity", "x, y = y, x", "return np.hypot(x, y)"), "PHI"),
        (
            body(
                "acc = np.zeros_like(s.x_velocity)",
                "for i in range(6):",
                "    acc += a[:, i] ** 2",
                "return -0.1 * acc",
                sig="s, a",
            ),
            "AUX",
        ),
        (body("return -np.sum(a * a, axis=-1) + 0.0 * np.linalg.norm(s.obs, axis=1)", sig="s, a"), "AUX"),
        (
            body(
                "if 1.0 > 0.5:",
                "    return np.clip(s.x_velocity, -3, 3)",
                "else:",
                "    return np.where(s.pitch > 0, s.pitch, 0.0)",
            ),
            "PHI",
        ),
        (body("return s.obs[:, 8] + s.obs[..., -1] * math.pi + np.e * 0.0"), "PHI"),
        (
            body("m = (s.pitch > 0.1) & ~(s.pitch > 2.0) | (s.pitch < -5)", "return np.where(m, 1.0, 0.0)"),
            "PHI",
        ),
        (
            body(
                "return np.round(s.x_velocity, 2) + np.max(s.obs, axis=(1,)) * 0 + abs(1.0) + max(1.0, 2.0)"
            ),
            "PHI",
        ),
        ("def f(s) -> np.ndarray:\n    return float(1.0) * s.torso_height\n", "PHI"),
    ],
)
def test_factor_language_is_admitted(code: str, kind: str) -> None:
    assert check_code("f", kind, code, FEATURES) == []
    fn = compile_factor("f", kind, code, FEATURES)
    assert callable(fn)


def test_example_programs_pass_static_checks() -> None:
    assert {(t, v) for t, v in example_programs()} >= {
        ("halfcheetah", 0),
        ("halfcheetah", 1),
        ("humanoidstandup", 0),
        ("humanoidstandup", 1),
    }
    for task, version in example_programs():
        report = check_program(example_program(task, version), load_task(task, check_env=False))
        assert report.ok and not report.violations, report.lines()


# ------------------------------------------------------------------ hostile corpus

HOSTILE: list[tuple[str, str, str, str]] = [
    # (id, code, kind, expected rule)
    ("import", "import os\n" + body("return s.x_velocity"), "PHI", "import"),
    ("import-in-body", body("import os", "return s.x_velocity"), "PHI", "import"),
    ("from-import", body("from os import system", "return s.x_velocity"), "PHI", "import"),
    ("dunder-import", body("m = __import__('os')", "return s.x_velocity"), "PHI", "import"),
    ("importlib", body("m = importlib.import_module('os')", "return s.x_velocity"), "PHI", "import"),
    ("eval", body("return eval('1')"), "PHI", "builtin"),
    ("exec", body("exec('x = 1')", "return s.x_velocity"), "PHI", "builtin"),
    ("bare-call", body("np.sum(s.obs)", "return s.x_velocity"), "PHI", "construct"),
    ("exec-value", body("x = exec", "return s.x_velocity"), "PHI", "builtin"),
    ("open", body(f"h = open('{MARKER}', 'w')", "return s.x_velocity"), "PHI", "builtin"),
    ("compile", body("c = compile('1', 'x', 'eval')", "return s.x_velocity"), "PHI", "builtin"),
    ("getattr", body("g = getattr(s, 'obs')", "return g"), "PHI", "builtin"),
    ("globals", body("g = globals()", "return s.x_velocity"), "PHI", "builtin"),
    ("vars", body("g = vars(np)", "return s.x_velocity"), "PHI", "builtin"),
    ("print", body("x = print(1)", "return s.x_velocity"), "PHI", "builtin"),
    (
        "subclasses",
        body("x = ().__class__.__bases__[0].__subclasses__()", "return s.x_velocity"),
        "PHI",
        "dunder",
    ),
    ("s-class", body("return s.__class__"), "PHI", "dunder"),
    ("s-dict", body("return s._values"), "PHI", "dunder"),
    ("np-dict", body("d = np.__dict__", "return s.x_velocity"), "PHI", "dunder"),
    ("array-interface", body("return a.__array_interface__", sig="s, a"), "AUX", "dunder"),
    ("func-globals", body("g = np.sum.__globals__", "return s.x_velocity"), "PHI", "dunder"),
    ("np-load", body("x = np.load('/etc/passwd')", "return s.x_velocity"), "PHI", "numpy"),
    ("np-save", body("x = np.save('x.npy', s.obs)", "return s.x_velocity"), "PHI", "numpy"),
    ("np-fromfile", body("x = np.fromfile('/etc/passwd')", "return s.x_velocity"), "PHI", "numpy"),
    ("np-memmap", body("x = np.memmap('x', mode='w+', shape=(4,))", "return s.x_velocity"), "PHI", "numpy"),
    ("np-lib", body("x = np.lib.npyio.savetxt('x', s.obs)", "return s.x_velocity"), "PHI", "numpy"),
    ("np-ctypeslib", body("x = np.ctypeslib.as_array(s.obs)", "return s.x_velocity"), "PHI", "numpy"),
    ("np-frompyfunc", body("f2 = np.frompyfunc(abs, 1, 1)", "return s.x_velocity"), "PHI", "numpy"),
    ("np-vectorize", body("x = np.vectorize(abs)(s.x_velocity)", "return x"), "PHI", "numpy"),
    ("np-random", body("return np.random.rand(3)"), "PHI", "numpy"),
    ("np-ones", body("return np.ones(10**12)"), "PHI", "numpy"),
    ("np-inf", body("return s.x_velocity * np.inf"), "PHI", "numpy"),
    ("np-func-as-value", body("f2 = np.sum", "return s.x_velocity"), "PHI", "numpy"),
    ("module-level-code", f"open('{MARKER}', 'w')\n" + body("return s.x_velocity"), "PHI", "module"),
    ("module-level-assign", "X = 1\n" + body("return s.x_velocity"), "PHI", "module"),
    ("two-defs", body("return s.x_velocity") + "def g(s):\n    return s.pitch\n", "PHI", "module"),
    ("no-def", "x = 1\n", "PHI", "module"),
    ("default-code", "def f(s, x=open('" + MARKER + "', 'w')):\n    return s.x_velocity\n", "PHI", "default"),
    ("default-list", "def f(s, cache=[]):\n    return s.x_velocity\n", "PHI", "default"),
    ("decorator", "@print\n" + body("return s.x_velocity"), "PHI", "decorator"),
    (
        "annotation-code",
        "def f(s: open('" + MARKER + "', 'w')):\n    return s.x_velocity\n",
        "PHI",
        "annotation",
    ),
    ("wrong-name", "def g(s):\n    return s.x_velocity\n", "PHI", "signature"),
    ("varargs", "def f(*s):\n    return 1.0\n", "PHI", "signature"),
    ("async", "async def f(s):\n    return s.x_velocity\n", "PHI", "module"),
    ("while-true", body("while True:", "    pass", "return s.x_velocity"), "PHI", "loop"),
    ("huge-range", body("for i in range(10**12):", "    pass", "return s.x_velocity"), "PHI", "loop"),
    ("big-range", body("for i in range(100000):", "    pass", "return s.x_velocity"), "PHI", "loop"),
    (
        "nested-range",
        body("for i in range(200):", "    for j in range(200):", "        pass", "return s.pitch"),
        "PHI",
        "loop",
    ),
    ("range-over-array", body("for v in s.obs:", "    pass", "return s.pitch"), "PHI", "loop"),
    (
        "loop-var-arith",
        body("x = 0.0", "for i in range(8):", "    x = x + i", "return s.pitch + x"),
        "PHI",
        "loop-var",
    ),
    ("recursion", body("return f(s)"), "PHI", "recursion"),
    ("power-tower", body("return 10**10**10 + s.x_velocity"), "PHI", "power"),
    ("power-var", body("return s.x_velocity ** s.pitch"), "PHI", "power"),
    ("power-big", body("return s.x_velocity ** 1000"), "PHI", "power"),
    ("np-power-var", body("return np.power(s.x_velocity, s.pitch)"), "PHI", "power"),
    ("huge-int", body("return s.x_velocity * 10000000000000000000000"), "PHI", "constant"),
    ("inf-literal", body("return s.x_velocity * 1e999"), "PHI", "constant"),
    ("complex", body("return s.x_velocity * 1j"), "PHI", "constant"),
    ("string", body("return 'abc'"), "PHI", "string"),
    ("fstring", body("x = f'{s}'", "return s.x_velocity"), "PHI", "string"),
    ("bytes", body("x = b'abc'", "return s.x_velocity"), "PHI", "string"),
    ("phi-reads-a", body("return a[:, 0]"), "PHI", "phi-action"),
    ("phi-signature-a", body("return s.x_velocity", sig="s, a"), "PHI", "phi-action"),
    ("phi-a-attr", body("return a.sum()"), "PHI", "phi-action"),
    ("future-feature", body("return s.next_x_velocity"), "PHI", "feature"),
    ("undeclared-feature", body("return s.qpos"), "PHI", "feature"),
    ("function-attr", body("f.count = 1", "return s.x_velocity"), "PHI", "mutation"),
    ("item-assign", body("x = s.obs", "x[0] = 1.0", "return s.x_velocity"), "PHI", "mutation"),
    ("assign-np", body("np = 1.0", "return s.x_velocity"), "PHI", "mutation"),
    ("assign-s", body("s = 1.0", "return s"), "PHI", "mutation"),
    ("global", body("global counter", "return s.x_velocity"), "PHI", "global"),
    ("nonlocal", body("nonlocal counter", "return s.x_velocity"), "PHI", "global"),
    ("lambda", body("g = lambda x: x", "return s.x_velocity"), "PHI", "construct"),
    ("listcomp", body("x = [v for v in range(3)]", "return s.x_velocity"), "PHI", "construct"),
    ("genexp", body("return sum(v for v in s.obs)"), "PHI", "construct"),
    ("list", body("x = [1.0, 2.0]", "return s.x_velocity"), "PHI", "construct"),
    ("dict", body("x = {}", "return s.x_velocity"), "PHI", "construct"),
    ("tuple-value", body("t = (s.x_velocity,)", "return s.x_velocity"), "PHI", "construct"),
    (
        "try",
        body("try:", "    x = 1.0", "except Exception:", "    x = 2.0", "return s.x_velocity"),
        "PHI",
        "construct",
    ),
    ("with", body("with np.errstate():", "    pass", "return s.x_velocity"), "PHI", "construct"),
    ("yield", body("yield s.x_velocity"), "PHI", "construct"),
    ("await", "async def f(s):\n    await s\n", "PHI", "module"),
    ("del", body("x = 1.0", "del x", "return s.x_velocity"), "PHI", "construct"),
    ("starred", body("return np.maximum(*s.obs)"), "PHI", "construct"),
    ("walrus", body("return (x := s.x_velocity)"), "PHI", "construct"),
    ("class", body("class K:", "    pass", "return s.x_velocity"), "PHI", "construct"),
    ("nested-def", body("def g():", "    return 1.0", "return s.x_velocity"), "PHI", "construct"),
    ("raise", body("raise ValueError"), "PHI", "construct"),
    ("assert", body("assert True", "return s.x_velocity"), "PHI", "construct"),
    ("not", body("return np.where(not s.pitch, 1.0, 0.0)"), "PHI", "construct"),
    ("is", body("return s.x_velocity if s.pitch is None else s.pitch"), "PHI", "construct"),
    ("matmul", body("return s.obs @ s.obs[0]"), "PHI", "construct"),
    ("shift", body("return s.x_velocity << 2"), "PHI", "construct"),
    ("slice", body("return np.sum(s.obs[:, 0:1] * s.x_velocity, axis=-1)"), "PHI", "subscript"),
    ("new-axis", body("return s.obs[:, None]"), "PHI", "subscript"),
    ("keepdims", body("return np.sum(s.obs, axis=1, keepdims=True)"), "PHI", "call"),
    ("dtype-object", body("return np.zeros_like(s.obs, dtype=object)"), "PHI", "call"),
    ("out-kw", body("return np.add(s.x_velocity, 1.0, out=s.x_velocity)"), "PHI", "numpy"),
    ("call-local", body("g = s.x_velocity", "return g()"), "PHI", "call"),
    ("s-as-value", body("return np.ones_like(s)"), "PHI", "attribute"),
    ("array-method", body("return s.obs.sum(axis=1)"), "PHI", "attribute"),
    ("math-func", body("return math.sqrt(2.0) * s.x_velocity"), "PHI", "attribute"),
    ("bare-return", body("return"), "PHI", "return"),
    ("no-return", body("x = s.x_velocity"), "PHI", "return"),
    ("syntax", "def f(s)\n    return 1\n", "PHI", "syntax"),
    ("too-long", body("x = s.x_velocity", *["x = x + 1.0"] * 800, "return x"), "PHI", "size"),
    ("deep", body("return " + "-" * 100 + "s.x_velocity"), "PHI", "size"),
    (
        "loop-cost",
        body(
            "x = s.x_velocity",
            "for i in range(256):",
            *["    x = x * 1.0 + x * 2.0 - x / 3.0 + np.tanh(x) * 0.5"],
            "return x",
        ),
        "PHI",
        "size",
    ),
    ("break-outside", body("break", "return s.x_velocity"), "PHI", "construct"),
    ("underscore-local", body("_x = s.x_velocity", "return _x"), "PHI", "dunder"),
]


@pytest.mark.parametrize("case", HOSTILE, ids=[c[0] for c in HOSTILE])
def test_hostile_code_is_rejected_with_rule_and_line(case: tuple[str, str, str, str]) -> None:
    _, code, kind, rule = case
    violations = check_code("f", kind, code, FEATURES)
    found = {v.rule for v in violations if v.is_error}
    assert rule in found, (found, [str(v) for v in violations])
    for v in violations:
        assert v.factor == "f" and v.rule in RULES and v.line >= 0 and v.message
        assert str(v).startswith(("f:", "warning: f:"))
    with pytest.raises(InadmissibleCodeError):
        compile_factor("f", kind, code, FEATURES)


def test_rejection_names_the_line() -> None:
    code = body("x = s.x_velocity", "y = eval('1')", "return x")
    [v] = [v for v in check_code("f", "PHI", code, FEATURES) if v.rule == "builtin"]
    assert v.line == 3 and v.factor == "f" and "eval" in v.message


def test_hostile_code_has_no_side_effect_and_cannot_be_compiled(tmp_path: Path) -> None:
    marker = tmp_path / "marker"
    attempts = [
        body(f"h = open('{marker}', 'w')", "return s.x_velocity"),
        f"open('{marker}', 'w')\n" + body("return s.x_velocity"),
        f"def f(s, h=open('{marker}', 'w')):\n    return s.x_velocity\n",
        f"@open('{marker}', 'w').write\n" + body("return s.x_velocity"),
        body("c = ().__class__.__base__.__subclasses__()", "return s.x_velocity"),
        body(f"np.save('{marker}', s.obs)", "return s.x_velocity"),
    ]
    card = load_task("halfcheetah", check_env=False)
    for code in attempts:
        assert rules(code), code
        with pytest.raises(InadmissibleCodeError):
            compile_factor("f", "PHI", code, FEATURES)
        program = FactorProgram("halfcheetah", 0, (Factor("f", "PHI", code, "d", "u", "[0, 1]"),))
        with pytest.raises(InadmissibleCodeError):
            CompiledProgram(program, card)
    assert not marker.exists()
    assert not os.path.exists(MARKER)


def test_feature_check_uses_the_card() -> None:
    assert rules(body("return s.uprightness")) == {"feature"}
    assert check_code("f", "PHI", body("return s.uprightness"), None) == []


def test_metadata_is_required_and_range_hint_parsed() -> None:
    bare = Factor("f", "PHI", body("return s.x_velocity"))
    found = check_metadata(bare)
    assert {v.rule for v in found} == {"metadata"} and all(v.is_error for v in found)
    odd = Factor("f", "PHI", body("return s.x_velocity"), "doc", "m/s", "roughly -1 to 1")
    [w] = check_metadata(odd)
    assert w.rule == "range-hint" and not w.is_error
    assert parse_range_hint("[-15, 15]") == (-15.0, 15.0)
    assert parse_range_hint("(0, inf)") == (0.0, float("inf"))
    assert parse_range_hint("[2, 1]") is None


def test_program_needs_a_phi_factor() -> None:
    program = FactorProgram(
        "halfcheetah",
        0,
        (Factor("c", "AUX", "def c(s, a):\n    return -np.sum(a * a, axis=-1)\n", "d", "u", "[-6, 0]"),),
    )
    assert "program" in {v.rule for v in check_program(program, FEATURES).errors}


def test_compiled_code_runs_with_empty_builtins_and_numpy_scalars() -> None:
    code = body(
        "b = (1.0 < 2.0) + (1.0 < 2.0)", "x = 2", *["x = x * x"] * 40, "return s.x_velocity * 0.0 + x + b"
    )
    assert check_code("f", "PHI", code, FEATURES) == []
    fn = compile_factor("f", "PHI", code, FEATURES)
    assert fn.__globals__["__builtins__"] == {}

    class View:
        x_velocity = np.ones(3)

    with np.errstate(over="ignore"):
        out = fn(View())  # Python ints would square 40 times into a 10^(10^11)-digit number; NumPy gives inf
    assert out.shape == (3,) and np.all(np.isinf(out))
