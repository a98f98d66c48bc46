"""Linear return decomposition: a per-step reward ``r̂ = xᵀθ`` fitted so that episode sums match returns.

With trajectory feedback only an episode's return R(τ) is observed. If the per-step reward is linear
in some per-step features, ``r(s, a, s′) = x(s, a, s′)ᵀθ``, the return is linear in the episode's
*summed* features, ``R(τ) = (Σ_t x_t)ᵀθ``, so θ is a least-squares problem over episodes (Efroni,
Merlis and Mannor 2021; the "reward decomposability" and "parametric alignment" of the MIRA paper's
section 3). Both the RD baseline (features ``[s, a, a², 1]``) and HARS's decomposition head (the
program's factors) fit it with :class:`EpisodeSumRegression`.

Only each episode's summed features, return and length are kept (O(d) per episode, a ring of at
most ``max_episodes``, oldest dropped), never its transitions. The ridge penalty is taken in
standardised units, ``ridge · diag(XᵀX)/n``: summed features of very different magnitudes are
shrunk alike, and ``ridge = 1`` weighs like one pseudo-episode pulling every weight to zero, which
washes out as episodes accumulate. A tiny absolute jitter keeps the system solvable when a feature is
identically zero.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class EpisodeSumRegression:
    """Ridge regression of episodic returns on per-episode summed features, refitted in closed form.

    The ridge is in standardised units: ``ridge`` pseudo-episodes, each feature's penalty scaled by its
    mean square over the stored episodes or, with ``centred``, by its variance across them. Centred, a
    feature with a large mean and little spread (a control cost, the per-step bias on fixed-length
    episodes) is penalised by what its spread says, not by its size, so the fit is not pulled away
    from the weights the returns identify. With ``select``, each fit takes the ridge among ``ridge · 10⁻ᵏ``
    (k = 0 … 6) with the smallest leave-one-episode-out error (closed form): strong while a handful of
    episodes leave the weights undetermined, weak once many pin them down, as the returns decide.
    """

    SELECT_DECADES = 7

    def __init__(self, dim: int, *, ridge: float = 1.0, max_episodes: int = 5_000, centred: bool = False,
                 select: bool = False) -> None:
        if dim <= 0:
            raise ValueError(f"feature dimension must be positive, not {dim}")
        if ridge < 0:
            raise ValueError(f"ridge must be >= 0, not {ridge}")
        if max_episodes <= 0:
            raise ValueError(f"max_episodes must be positive, not {max_episodes}")
        self.dim = int(dim)
        self.ridge = float(ridge)
        self.centred = bool(centred)
        self.select = bool(select)
        self.chosen_ridge = float(ridge)
        """The ridge of the last fit (``ridge`` itself unless ``select``)."""
        self.max_episodes = int(max_episodes)
        self.sums = np.zeros((0, self.dim), dtype=np.float64)
        self.returns = np.zeros(0, dtype=np.float64)
        self.lengths = np.zeros(0, dtype=np.float64)
        self.count = 0  # episodes held (<= max_episodes)
        self.head = 0  # next slot to overwrite once the ring is full
        self.fits = 0
        self.theta: np.ndarray = np.zeros(self.dim, dtype=np.float64)
        self.loss = float("nan")
        """Mean squared per-step residual ((R − Σxᵀθ)/T)² over the stored episodes at the last fit."""
        self.r2 = float("nan")
        """Fraction of the variance of the stored returns the last fit explains."""

    @classmethod
    def of(cls, sums: np.ndarray, returns: np.ndarray, lengths: np.ndarray, *, ridge: float = 1.0,
           centred: bool = False, select: bool = False) -> EpisodeSumRegression:
        """A regression holding the given episodes (summed features ``[E, dim]``, returns, lengths)."""
        reg = cls(sums.shape[1], ridge=ridge, max_episodes=max(1, sums.shape[0]), centred=centred, select=select)
        n = sums.shape[0]
        reg.sums = np.asarray(sums, dtype=np.float64).copy()
        reg.returns = np.asarray(returns, dtype=np.float64).reshape(n).copy()
        reg.lengths = np.asarray(lengths, dtype=np.float64).reshape(n).copy()
        reg.count = n
        return reg

    def add(self, summed: np.ndarray, episode_return: float, length: float) -> None:
        """Remember one episode's summed features ``[dim]``, its return and its length."""
        summed = np.asarray(summed, dtype=np.float64).reshape(self.dim)
        if self.count < self.max_episodes:
            if self.count == self.sums.shape[0]:  # grow geometrically up to the cap
                new = min(self.max_episodes, max(16, 2 * self.sums.shape[0]))
                self.sums = np.concatenate((self.sums, np.zeros((new - self.count, self.dim))))
                self.returns = np.concatenate((self.returns, np.zeros(new - self.count)))
                self.lengths = np.concatenate((self.lengths, np.zeros(new - self.count)))
            slot = self.count
            self.count += 1
        else:
            slot = self.head
            self.head = (self.head + 1) % self.max_episodes
        self.sums[slot], self.returns[slot], self.lengths[slot] = summed, float(episode_return), float(length)

    def fit(self) -> np.ndarray:
        """Solve the ridge problem on every stored episode; returns θ̂ (float64, also kept in ``theta``)."""
        n = self.count
        if n == 0:
            return self.theta
        x, r, t = self.sums[:n], self.returns[:n], self.lengths[:n]
        a = x.T @ x
        diag = np.diag(a).copy()
        jitter = 1e-10 * max(float(diag.mean()), 1e-12)
        # (ridge · diag) / n in that order when uncentred: the earlier form, bit for bit.
        scale, per = (x.var(axis=0), 1.0) if self.centred else (diag, float(n))
        b = x.T @ r
        self.chosen_ridge = self._loo_ridge(x, r, a, b, scale / per, jitter) if self.select and n > 2 else self.ridge
        a_reg = a + np.diag(self.chosen_ridge * scale / per + jitter)
        try:
            theta = np.linalg.solve(a_reg, b)
        except np.linalg.LinAlgError:
            theta = np.linalg.lstsq(a_reg, b, rcond=None)[0]
        if not np.all(np.isfinite(theta)):
            theta = np.zeros_like(theta)
        pred = x @ theta
        resid = r - pred
        self.loss = float(np.mean((resid / np.maximum(t, 1.0)) ** 2))
        var = float(np.var(r))
        self.r2 = 1.0 - float(np.mean(resid**2)) / var if var > 0 else float("nan")
        self.theta = theta
        self.fits += 1
        return theta

    def _loo_ridge(self, x: np.ndarray, r: np.ndarray, a: np.ndarray, b: np.ndarray, scale: np.ndarray,
                   jitter: float) -> float:
        """The grid's ridge with the smallest leave-one-out squared error: eᵢ / (1 − hᵢᵢ) per episode."""
        best, best_err = self.ridge, float("inf")
        for k in range(self.SELECT_DECADES):
            lam = self.ridge * 10.0**-k
            try:
                inv = np.linalg.inv(a + np.diag(lam * scale + jitter))
            except np.linalg.LinAlgError:
                continue
            h = np.einsum("ij,jk,ik->i", x, inv, x)
            loo = (r - x @ (inv @ b)) / np.maximum(1.0 - h, 1e-9)
            err = float(np.mean(loo**2))
            if np.isfinite(err) and err < best_err:
                best, best_err = lam, err
        return best

    def state_dict(self) -> dict[str, Any]:
        n = self.count
        return {"sums": self.sums[:n].copy(), "returns": self.returns[:n].copy(), "lengths": self.lengths[:n].copy(),
                "head": self.head, "fits": self.fits, "theta": self.theta.copy(), "loss": self.loss, "r2": self.r2}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        sums = np.asarray(state["sums"], dtype=np.float64).reshape(-1, self.dim)
        self.sums = sums.copy()
        self.returns = np.asarray(state["returns"], dtype=np.float64).copy()
        self.lengths = np.asarray(state["lengths"], dtype=np.float64).copy()
        self.count = int(sums.shape[0])
        self.head = int(state["head"])
        self.fits = int(state["fits"])
        self.theta = np.asarray(state["theta"], dtype=np.float64).reshape(self.dim).copy()
        self.loss = float(state["loss"])
        self.r2 = float(state.get("r2", float("nan")))

