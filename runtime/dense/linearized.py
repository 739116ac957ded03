"""The decoder cache of a keyframe: the network linearised at a code (Sec. 5.3, Eq. 16-17).

The exact decoder and its finite-difference Jacobian (Eq. 17, one batch of C+1 codes) are evaluated at a
linearisation point: c = 0 after the prior, then a code an optimisation gave once it moved more than
``relin_tol`` from the last point (:mod:`runtime.dense.mapper`). During LM the depth map is the first-order
expansion ``D(c0) + J(c0) (c - c0)``, which the factors evaluate only at their pixels (:meth:`expansion`), so LM
runs Gauss-Newton steps on the linearised decoder. The exact decoder is used for the outputs and the depth
metrics; :class:`ApproxErrorProbe` measures what the expansion costs."""

from __future__ import annotations

import numpy as np

from runtime.dense.lookup import MapExpansion

__all__ = ["LinearizedDepth", "ApproxErrorProbe"]


class LinearizedDepth:
    """A keyframe's depth provider, relinearised by :meth:`relinearize` and first order in between.

    Wraps a :class:`runtime.network.KeyframeDepth`-like object ``kd`` (``uncertainty``, ``net``, ``depth``,
    ``jacobian``).
    """

    def __init__(self, kd) -> None:
        self.kd = kd
        self.net = kd.net
        self.code_dim = kd.net.code_dim
        self.uncertainty = kd.uncertainty
        self.c0: np.ndarray | None = None
        self.D0: np.ndarray | None = None
        self.J0: np.ndarray | None = None
        self.n_relin = 0

    def _relin(self, code: np.ndarray) -> None:
        self.D0, self.J0 = self.kd.jacobian(code)
        self.D0 = self.D0.astype(np.float64)
        self.J0 = self.J0.astype(np.float64)
        self.c0 = np.asarray(code, np.float32).astype(np.float64)
        self.n_relin += 1

    def jacobian(self, code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth (H, W) and ``dD/dc`` (H, W, C) of the expansion at ``code``, the whole map (exact at the
        linearisation point; the first call before any :meth:`relinearize` linearises at ``code``). The factors
        use :meth:`expansion` instead, which forms no map."""
        e = self.expansion(code)
        return (self.D0 if e.dc is None else self.D0 + self.J0 @ e.dc), self.J0

    def depth(self, code: np.ndarray) -> np.ndarray:
        return self.jacobian(code)[0]

    def expansion(self, code: np.ndarray) -> MapExpansion:
        """The expansion at ``code`` for the factors, evaluated only where they look (the same values as
        :meth:`jacobian`'s maps; the first call before any :meth:`relinearize` linearises at ``code``)."""
        if self.c0 is None:
            self._relin(code)
        return MapExpansion(self.D0, self.J0, np.asarray(code, np.float64) - self.c0)

    def relinearize(self, code: np.ndarray) -> None:
        """Exact decoder and Jacobian at ``code`` unless it is the current linearisation point (compared as the
        float32 code the network sees)."""
        c = np.asarray(code, np.float32).astype(np.float64)
        if self.c0 is None or not np.array_equal(c, self.c0):
            self._relin(code)

    def exact(self, code: np.ndarray) -> np.ndarray:
        return self.kd.depth(code)


class ApproxErrorProbe:
    """Diagnostic: after each optimisation, decode the code keyframes' final codes exactly once more and record
    the expansion's error ``|D_lin(c) - D(c)|`` (costs one decoder run per code keyframe and optimisation).

    ``DenseMapper(..., probe=ApproxErrorProbe())``; the mapper's metrics then carry ``approx_error_mean_m`` and
    ``approx_error_max_m``.
    """

    def __init__(self) -> None:
        self.err_mean: list[float] = []
        self.err_max: list[float] = []

    def __call__(self, keyframes) -> None:
        """``keyframes``: ``(provider, code)`` pairs of the code keyframes (:class:`LinearizedDepth`, (C,))."""
        errs = [np.abs(p.depth(code) - p.exact(code)) for p, code in keyframes]
        if errs:
            e = np.concatenate([x.ravel() for x in errs])
            self.err_mean.append(float(e.mean()))
            self.err_max.append(float(e.max()))

    def metrics(self) -> dict:
        if not self.err_mean:
            return {}
        return {"approx_error_mean_m": float(np.mean(self.err_mean)), "approx_error_max_m": float(np.max(self.err_max))}
