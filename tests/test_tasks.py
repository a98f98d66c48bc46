from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from mira.errors import TaskCardError
from mira.tasks import builtin_task_names, load_task, make_env

REQUIRED = {
    "halfcheetah": {"x_velocity", "z_velocity", "torso_height", "pitch", "pitch_rate"},
    "humanoidstandup": {"torso_height", "z_velocity", "x_velocity", "y_velocity"},
    "humanoid": {"torso_height", "z_velocity", "x_velocity", "y_velocity"},
}


def test_builtin_cards_exist_with_required_features() -> None:
    assert set(REQUIRED) <= set(builtin_task_names())
    for name, needed in REQUIRED.items():
        card = load_task(name)
        assert needed <= set(card.feature_names), name


@pytest.mark.parametrize("name", sorted(REQUIRED))
def test_feature_indices_match_mujoco_layout(name: str) -> None:
    """Set random qpos/qvel in the simulator and check each feature reads the documented quantity."""
    card = load_task(name)
    env = gym.make(card.env_id)
    env.reset(seed=0)
    base = env.unwrapped
    rng = np.random.default_rng(0)
    base.data.qpos[:] = rng.normal(size=base.model.nq)
    base.data.qvel[:] = rng.normal(size=base.model.nv)
    obs = base._get_obs()
    card.bind(obs.shape[0])
    values = card.feature_values(obs[None, :])
    checked = 0
    for feat in card.features:
        if feat.source is None:
            continue
        kind, idx = feat.source.split(":")
        expected = (base.data.qpos if kind == "qpos" else base.data.qvel)[int(idx)]
        assert values[feat.name][0] == pytest.approx(expected), feat.name
        checked += 1
    assert checked >= 4


def test_uprightness_expression_is_one_when_upright() -> None:
    card = load_task("humanoid")
    env = make_env(card)
    obs, _ = env.reset(seed=1)
    view = card.state_view(obs)
    assert view.uprightness[0] == pytest.approx(1.0, abs=0.05)
    with pytest.raises(AttributeError):
        view.torso_height = np.zeros(1)  # type: ignore[misc]
    with pytest.raises(ValueError):
        view.torso_height[0] = 3.0

def test_humanoidstandup_uprightness_follows_the_pelvis_to_head_axis() -> None:
    """HumanoidStandup's model lies along +x in its reference pose (identity quaternion): uprightness
    is 0 at the start and 1 once the head is straight above the pelvis, -1 head down."""
    import mujoco

    card = load_task("humanoidstandup")
    env = make_env(card)
    obs, _ = env.reset(seed=1)
    assert card.state_view(obs[None]).uprightness[0] == pytest.approx(0.0, abs=0.05)
    base = env.unwrapped
    model, data = base.model, base.data  # type: ignore[attr-defined]
    head = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "head")
    butt = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "butt")
    for pitch, expected in ((90.0, 1.0), (-90.0, -1.0), (45.0, np.sqrt(0.5))):
        half = np.radians(pitch) / 2
        data.qpos[2] = 1.0
        data.qpos[3:7] = [np.cos(half), 0.0, np.sin(half), 0.0]
        mujoco.mj_forward(model, data)
        view = card.state_view(base._get_obs()[None])  # type: ignore[attr-defined]
        assert view.uprightness[0] == pytest.approx(expected, abs=1e-6)
        assert (data.geom_xpos[head][2] > data.geom_xpos[butt][2]) == (expected > 0)


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


CARD = """
name = "pendulum"
env_id = "InvertedPendulum-v5"
description = "keep the pole upright"
[action]
doc = "force on the cart"
[[features]]
name = "angle"
index = {index}
units = "rad"
doc = "pole angle"
"""


def test_user_card_toml_and_yaml(tmp_path: Path) -> None:
    card = load_task(str(_write(tmp_path, "p.toml", CARD.format(index=1))))
    env = make_env(card)
    obs, _ = env.reset(seed=0)
    assert card.feature_values(obs)["angle"][0] == pytest.approx(obs[1])
    yaml_card = _write(
        tmp_path, "p.yaml",
        "name: p\nenv_id: InvertedPendulum-v5\ndescription: d\naction: {doc: force}\n"
        "features:\n  - {name: angle, expr: 'obs[1] * 2', units: rad, doc: twice}\n",
    )
    card2 = load_task(str(yaml_card))
    make_env(card2)
    assert card2.feature_values(obs)["angle"][0] == pytest.approx(2 * obs[1])


def test_card_with_missing_index_fails_clearly(tmp_path: Path) -> None:
    card = load_task(str(_write(tmp_path, "p.toml", CARD.format(index=99))))
    with pytest.raises(TaskCardError, match=r"obs\[99\].*4 entries"):
        make_env(card)


def test_card_with_unknown_env_fails_clearly(tmp_path: Path) -> None:
    with pytest.raises(TaskCardError, match="NoSuchEnv-v0"):
        load_task(str(_write(tmp_path, "p.toml", CARD.format(index=0).replace("InvertedPendulum-v5", "NoSuchEnv-v0"))))


@pytest.mark.parametrize(
    ("expr", "message"),
    [("__import__('os')", "not allowed"), ("obs[1] ** obs[2]", "small constant exponent"), ("obs.T", "not allowed")],
)
def test_feature_expressions_are_whitelisted(tmp_path: Path, expr: str, message: str) -> None:
    text = CARD.format(index=0).replace("index = 0", f'expr = "{expr}"')
    with pytest.raises(TaskCardError, match=message):
        load_task(str(_write(tmp_path, "p.toml", text)))


def test_unknown_task_name() -> None:
    with pytest.raises(TaskCardError, match="unknown task 'walker'"):
        load_task("walker")


# ------------------------------------------------------------------------------ cards that say what is wrong
@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace('description = "keep', 'eval_horizn = 500\ndescription = "keep'),
         r"p\.toml: unknown key 'eval_horizn'; did you mean 'eval_horizon'\?"),
        (lambda t: t.replace('doc = "force on the cart"', 'doc = "force on the cart"\nnmes = ["push"]'),
         r"p\.toml, action: unknown key 'nmes'; did you mean 'names'\?"),
        (lambda t: t.replace('units = "rad"', 'unit = "rad"'),
         r"p\.toml, features\[0\]: unknown key 'unit'; did you mean 'units'\?"),
        (lambda t: t.replace('name = "pendulum"', 'name = "pendulum\n'), r"p\.toml: does not parse as TOML: .*line 2"),
        (lambda t: "", r"p\.toml: the file is empty"),
        (lambda t: "  \n", r"p\.toml: the file is empty"),
        (lambda t: t.replace('units = "rad"', 'units = "rad"\nbetter = "up"'),
         r"p\.toml, features\[0\]: feature 'angle' key 'better' must be one of higher, lower, closer, not 'up'"),
        (lambda t: t.replace('units = "rad"', 'units = "rad"\nbetter = "higher"\ntarget = 1.0'),
         r"p\.toml, features\[0\]: feature 'angle' key 'target' must be a number, and only with better"),
        (lambda t: t.replace('units = "rad"', 'units = "rad"\nrange = [1.0, -1.0]'),
         r"p\.toml, features\[0\]: feature 'angle' key 'range' must be \[lo, hi\] with lo <= hi"),
    ],
)
def test_bad_cards_name_the_file_the_key_and_the_line(tmp_path: Path, edit: object, message: str) -> None:
    with pytest.raises(TaskCardError, match=message):
        load_task(str(_write(tmp_path, "p.toml", edit(CARD.format(index=1)))))  # type: ignore[operator]


def test_yaml_parse_errors_give_line_and_column(tmp_path: Path) -> None:
    text = "name: p\nenv_id: InvertedPendulum-v5\ndescription: [unclosed\naction: {doc: force}\n"
    with pytest.raises(TaskCardError, match=r"p\.yaml: does not parse as YAML: .*\(at line \d+, column \d+\)"):
        load_task(str(_write(tmp_path, "p.yaml", text)))
    with pytest.raises(TaskCardError, match=r"p2\.yaml: the file is empty"):
        load_task(str(_write(tmp_path, "p2.yaml", "")))


def test_action_names_must_match_the_action_dimension(tmp_path: Path) -> None:
    text = CARD.format(index=1).replace('doc = "force on the cart"', 'doc = "force"\nnames = ["push", "pull"]')
    card = load_task(str(_write(tmp_path, "p.toml", text)))
    with pytest.raises(TaskCardError, match=r"p\.toml, action: key 'names' lists 2 names but .* has 1 action"):
        make_env(card)


def test_an_out_of_range_index_names_the_card_file(tmp_path: Path) -> None:
    card = load_task(str(_write(tmp_path, "p.toml", CARD.format(index=999))))
    with pytest.raises(TaskCardError, match=r"p\.toml, features\[0\] \('angle'\): reads obs\[999\], but .* 4 entries"):
        make_env(card)


def _doc_cards(tmp_path: Path) -> list[Path]:
    """The example cards of docs/task_cards.md, written out under their ``file=`` names."""
    import re

    doc = (Path(__file__).resolve().parents[1] / "docs" / "task_cards.md").read_text(encoding="utf-8")
    paths = []
    for name, body in re.findall(r"```(?:toml|yaml) file=(\S+)\n(.*?)```", doc, flags=re.S):
        paths.append(_write(tmp_path, name, body))
    return paths


def test_the_documented_example_cards_load_and_read_what_they_say(tmp_path: Path) -> None:
    paths = _doc_cards(tmp_path)
    assert {p.suffix for p in paths} == {".toml", ".yaml"} and len(paths) == 2
    for path in paths:
        card = load_task(str(path))
        env = make_env(card)
        env.reset(seed=0)
        base = env.unwrapped
        rng = np.random.default_rng(0)
        base.data.qpos[:] = rng.normal(size=base.model.nq)  # type: ignore[attr-defined]
        base.data.qvel[:] = rng.normal(size=base.model.nv)  # type: ignore[attr-defined]
        values = card.feature_values(base._get_obs()[None, :])  # type: ignore[attr-defined]
        for feat in card.features:
            if feat.source is not None:
                kind, idx = feat.source.split(":")
                expected = (base.data.qpos if kind == "qpos" else base.data.qvel)[int(idx)]  # type: ignore[attr-defined]
                assert values[feat.name][0] == pytest.approx(expected), (path.name, feat.name)


def test_mujoco_deprecation_noise_is_filtered_and_other_warnings_are_not(capfd: pytest.CaptureFixture[str]) -> None:
    import mujoco

    make_env(load_task("halfcheetah")).close()
    handler = mujoco.get_mju_user_warning()
    assert handler is not None
    handler("compiler attribute 'settotalmass' is deprecated and will be removed")
    handler("Nan, Inf or huge value in QACC at DOF 0")
    err = capfd.readouterr().err
    assert "settotalmass" not in err and "WARNING: Nan, Inf or huge value in QACC" in err
