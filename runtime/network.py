"""The exported depth network under ONNX Runtime (no torch): prior, decoder and the code Jacobian (Eq. 17).

A model directory holds ``prior.onnx``, ``decoder.onnx`` and ``manifest.json`` (written by ``dit-export``).
The manifest records each ONNX file's SHA-256 and the export's run id; a folder whose files do not match their
manifest (e.g. one graph of another export), or whose manifest records no hashes, is refused at load.

>>> net = DepthNetwork("models/default")                          # doctest: +SKIP
>>> kf = net.prior(grey_224, sparse_224)                          # doctest: +SKIP
>>> depth, J = kf.jacobian(np.zeros(8, np.float32))               # doctest: +SKIP
"""

from __future__ import annotations

import hashlib
import json
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.densify import network_fill

MODALITY_CHANNELS = {"rgb": 3, "rgbs": 4, "gray": 1, "grays": 2}
RUNTIME_MODALITIES = ("gray", "grays")  # the SLAM runtime feeds grey cam0 images (runtime.dense.DenseMapper)


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def verify_files(model_dir: Path, manifest: dict) -> None:
    """Check every file of the manifest's ``files`` (``{name: {"sha256": ...}}``) against its SHA-256.

    Raises:
        ModelError: the manifest records no file hashes (an export older than them: its files cannot be
            verified), a file is missing, or its bytes differ from the export that wrote the manifest.
    """
    files = manifest.get("files")
    run = manifest.get("run_id", "?")
    if not files or not isinstance(files, dict):
        raise ModelError(
            f"{model_dir}: manifest.json records no file hashes (written by an older dit-export), so its files "
            "cannot be verified; re-export the model with dit-export"
        )
    for name, rec in files.items():
        p = model_dir / name
        if not p.is_file():
            raise ModelError(f"{p}: missing (manifest.json of export {run} lists it)")
        if file_sha256(p) != rec.get("sha256"):
            raise ModelError(
                f"{p}: SHA-256 does not match manifest.json (export {run}): the folder mixes files of different "
                "exports or a file was changed; export the model again"
            )


def default_model_dir() -> Path:
    """The shipped default model (``runtime/assets/default_model``; how it was made: its README.md)."""
    return Path(__file__).resolve().parent / "assets" / "default_model"


class ModelError(ValueError):
    """A model directory that is missing, inconsistent, or does not match what the caller needs."""


@dataclass(frozen=True)
class SessionConfig:
    """ONNX Runtime options (chosen by ``benchmarks/bench_network.py``; see its JSON for the figures).

    Measured on the 2-core CPU with the backend sharing it: ``all`` is 1.2-1.6x faster than ``basic``/``disable``;
    1 thread beats 2; spinning costs 1.6-2.6x with 2 threads; the nominal code in the batch or apart is a wash.

    Attributes:
        threads: intra-op threads; never more than the cores the process may use.
        optimization: ``all`` | ``extended`` | ``basic`` | ``disable``.
        spinning: let idle ORT threads spin (faster alone, wasteful when GTSAM shares the CPU).
        nominal_in_batch: decode the nominal code in the same call as the 8 perturbed ones (batch 9).
    """

    threads: int = 1
    optimization: str = "all"
    spinning: bool = False
    nominal_in_batch: bool = True


def _session(path: Path, cfg: SessionConfig):
    import onnxruntime as ort

    levels = {
        "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
        "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
        "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
        "disable": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
    }
    if cfg.optimization not in levels:
        raise ValueError(f"optimization={cfg.optimization!r}: expected one of {sorted(levels)}")
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(cfg.threads)
    so.inter_op_num_threads = 1
    so.graph_optimization_level = levels[cfg.optimization]
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if cfg.spinning else "0")
    so.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        raise ModelError(f"{path}: ONNX Runtime cannot load it: {e}") from e


def _check_io(session, spec: list[dict], what: str, path: Path) -> None:
    actual = [(x.name, [d if isinstance(d, int) else "?" for d in x.shape]) for x in what_io(session, what)]
    expected = [(x["name"], [d if isinstance(d, int) else "?" for d in x["shape"]]) for x in spec]
    if actual != expected:
        raise ModelError(f"{path}: {what} {actual} do not match the manifest's {expected}")


def what_io(session, what: str):
    return session.get_inputs() if what == "inputs" else session.get_outputs()


class DepthNetwork:
    """Loads a model directory and checks the two graphs against the manifest and each other."""

    def __init__(self, model_dir: str | Path, session: SessionConfig | None = None):
        self.dir = Path(model_dir)
        manifest_path = self.dir / "manifest.json"
        if not manifest_path.is_file():
            raise ModelError(f"{manifest_path}: no manifest (expected the output of dit-export)")
        try:
            self.manifest = json.loads(manifest_path.read_text())
        except json.JSONDecodeError as e:
            raise ModelError(f"{manifest_path}: not valid JSON: {e}") from e
        m = self.manifest
        for key in ("modality", "in_channels", "height", "width", "code_dim", "prior", "decoder", "jacobian"):
            if key not in m:
                raise ModelError(f"{manifest_path}: missing key {key!r}")
        self.modality: str = m["modality"]
        self.height, self.width = int(m["height"]), int(m["width"])
        self.code_dim = int(m["code_dim"])
        self.in_channels = int(m["in_channels"])
        self.delta = float(m["jacobian"]["delta"])
        if MODALITY_CHANNELS.get(self.modality) != self.in_channels:
            raise ModelError(f"{manifest_path}: modality {self.modality!r} with {self.in_channels} input channels")
        verify_files(self.dir, m)
        self.run_id = m.get("run_id")
        self.session_config = session or SessionConfig()
        self._prior = _session(self.dir / m["prior"]["file"], self.session_config)
        self._decoder = _session(self.dir / m["decoder"]["file"], self.session_config)
        _check_io(self._prior, m["prior"]["inputs"], "inputs", self.dir / m["prior"]["file"])
        _check_io(self._prior, m["prior"]["outputs"], "outputs", self.dir / m["prior"]["file"])
        _check_io(self._decoder, m["decoder"]["inputs"], "inputs", self.dir / m["decoder"]["file"])
        _check_io(self._decoder, m["decoder"]["outputs"], "outputs", self.dir / m["decoder"]["file"])
        self.feature_names = [o.name for o in self._prior.get_outputs()[1:]]
        dec_feats = [i.name for i in self._decoder.get_inputs()[1:]]
        if dec_feats != self.feature_names:
            raise ModelError(f"{self.dir}: decoder takes {dec_feats}, prior gives {self.feature_names}")
        image_shape = [d if isinstance(d, int) else "?" for d in self._prior.get_inputs()[0].shape]
        if image_shape[1:] != [self.in_channels, self.height, self.width]:
            raise ModelError(
                f"{self.dir / m['prior']['file']}: input shape {image_shape} does not match the manifest's "
                f"{self.in_channels} channels of {self.height}x{self.width}"
            )
        #: relative model: prior.onnx also takes ``fill``, the interpolated sparse depth (runtime.densify)
        self.takes_fill = [i.name for i in self._prior.get_inputs()] == ["image", "fill"]
        self.decoder_calls = 0  # counts ORT decoder runs (tests and benchmarks read it)

    @property
    def uses_sparse(self) -> bool:
        return self.modality.endswith("s")

    def check_compatible(self, modality: str | None = None, size: tuple[int, int] | None = None) -> None:
        """Raise :class:`ModelError` when the caller needs another modality or network size."""
        if modality is not None and modality != self.modality:
            raise ModelError(f"{self.dir}: model is {self.modality!r}, the caller needs {modality!r}")
        if size is not None and tuple(size) != (self.height, self.width):
            raise ModelError(f"{self.dir}: model is {self.height}x{self.width}, the caller needs {size[0]}x{size[1]}")

    def check_runtime(self) -> DepthNetwork:
        """Raise :class:`ModelError` unless the SLAM runtime can feed this model (grey images, network size a
        multiple of 32); returns ``self``."""
        if self.modality not in RUNTIME_MODALITIES:
            raise ModelError(
                f"{self.dir}: model modality is {self.modality!r}; dit-slam feeds grey images and needs one of "
                f"{', '.join(RUNTIME_MODALITIES)}"
            )
        if self.height % 32 or self.width % 32 or self.height <= 0 or self.width <= 0:
            raise ModelError(f"{self.dir}: network size {self.height}x{self.width} is not a multiple of 32")
        return self

    # ------------------------------------------------------------------ inputs
    def make_input(self, image: np.ndarray, sparse: np.ndarray | None = None) -> np.ndarray:
        """Network input [1, Cin, H, W] from an image at network size and, for ``*s``, sparse depth [m].

        Args:
            image: (H, W) grey or (H, W, 3) RGB, uint8 (0-255) or float in [0, 1].
            sparse: (H, W) metres, 0 where no map point projects; required for ``grays``/``rgbs``.
        """
        img = np.asarray(image)
        if img.dtype == np.uint8:
            img = img.astype(np.float32) / 255.0
        img = img.astype(np.float32, copy=False)
        want_rgb = self.modality.startswith("rgb")
        if img.ndim == 3 and img.shape[2] == 3 and not want_rgb:
            img = img @ np.array([0.299, 0.587, 0.114], np.float32)  # BT.601 luma, as cv2's RGB2GRAY
        if want_rgb and not (img.ndim == 3 and img.shape[2] == 3):
            raise ModelError(f"model {self.modality!r} needs an RGB image (H, W, 3), got shape {img.shape}")
        if img.shape[:2] != (self.height, self.width):
            raise ModelError(f"image is {img.shape[1]}x{img.shape[0]}, the model takes {self.width}x{self.height}")
        chans = [img.transpose(2, 0, 1)] if img.ndim == 3 else [img[None]]
        if self.uses_sparse:
            if sparse is None:
                raise ModelError(f"model {self.modality!r} needs a sparse depth image")
            sp = np.asarray(sparse, np.float32)
            if sp.shape != (self.height, self.width):
                raise ModelError(f"sparse depth has shape {sp.shape}, the model takes {(self.height, self.width)}")
            if not np.isfinite(sp).all():
                raise ModelError("sparse depth has non-finite values")
            chans.append(sp[None])
        elif sparse is not None:
            raise ModelError(f"model {self.modality!r} takes no sparse depth")
        return np.ascontiguousarray(np.concatenate(chans, 0)[None])

    # ------------------------------------------------------------------ graphs
    def prior(self, image: np.ndarray, sparse: np.ndarray | None = None, cache_size: int = 4) -> KeyframeDepth:
        """Run ``prior.onnx`` once for a keyframe; the result decodes codes and caches them."""
        x = self.make_input(image, sparse)
        feed = {"image": x}
        if self.takes_fill:
            feed["fill"] = network_fill(x[0, -1])[None, None]
        outs = self._prior.run(None, feed)
        fill = feed["fill"][0, 0] if self.takes_fill else None
        feed = dict(zip(self.feature_names, outs[1:], strict=True))
        return KeyframeDepth(self, outs[0][0, 0], feed, cache_size=cache_size, fill=fill)

    def decode(self, codes: np.ndarray, features: dict[str, np.ndarray]) -> np.ndarray:
        """Depth [B, H, W] (metres) for codes [B, C] given a keyframe's features."""
        codes = np.ascontiguousarray(np.atleast_2d(codes), dtype=np.float32)
        if codes.shape[1] != self.code_dim:
            raise ModelError(f"codes have dimension {codes.shape[1]}, the model's is {self.code_dim}")
        self.decoder_calls += 1
        return self._decoder.run(None, {"code": codes, **features})[0][:, 0]


@dataclass
class KeyframeDepth:
    """One keyframe's network state: uncertainty map, decoder features, and a per-code cache."""

    net: DepthNetwork
    uncertainty: np.ndarray  # (H, W) metres, > 0
    features: dict[str, np.ndarray]
    cache_size: int = 4
    fill: np.ndarray | None = None  # (H, W) the prior's densified sparse input (a relative model's ``fill``), or None
    _depth: OrderedDict = field(default_factory=OrderedDict, repr=False)
    _jac: OrderedDict = field(default_factory=OrderedDict, repr=False)

    @staticmethod
    def _key(code: np.ndarray) -> bytes:
        return np.ascontiguousarray(code, dtype=np.float32).tobytes()

    def _remember(self, cache: OrderedDict, key: bytes, value) -> None:
        cache[key] = value
        cache.move_to_end(key)
        while len(cache) > self.cache_size:
            cache.popitem(last=False)

    def _check(self, code: np.ndarray) -> np.ndarray:
        code = np.asarray(code, dtype=np.float32).reshape(-1)
        if code.shape != (self.net.code_dim,):
            raise ModelError(f"code has shape {code.shape}, the model's code is ({self.net.code_dim},)")
        if not np.isfinite(code).all():
            raise ModelError(f"code has non-finite values: {code}")
        return code

    def depth(self, code: np.ndarray) -> np.ndarray:
        """Depth (H, W) [m] for one code; never decodes the same code twice."""
        code = self._check(code)
        key = self._key(code)
        if key in self._jac:
            return self._jac[key][0]
        if key not in self._depth:
            self._remember(self._depth, key, self.net.decode(code[None], self.features)[0])
        return self._depth[key]

    def jacobian(self, code: np.ndarray, delta: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Depth (H, W) and ``J`` (H, W, C) with ``J[:, :, i] = (F(c + delta e_i) - F(c)) / delta`` (Eq. 17).

        The C perturbed codes go through the decoder as one batch (with the nominal code too when
        ``SessionConfig.nominal_in_batch``, unless its depth is cached already).
        """
        code = self._check(code)
        delta = self.net.delta if delta is None else float(delta)
        key = self._key(code)
        if delta == self.net.delta and key in self._jac:
            return self._jac[key]
        C = self.net.code_dim
        perturbed = np.repeat(code[None], C, 0) + np.float32(delta) * np.eye(C, dtype=np.float32)
        have_nominal = key in self._depth
        if not have_nominal and self.net.session_config.nominal_in_batch:
            out = self.net.decode(np.concatenate([code[None], perturbed]), self.features)
            nominal, moved = out[0], out[1:]
        else:
            nominal = self._depth[key] if have_nominal else self.net.decode(code[None], self.features)[0]
            moved = self.net.decode(perturbed, self.features)
        # Divide by the step actually taken in float32, not the nominal delta.
        step = (perturbed[np.arange(C), np.arange(C)] - code).astype(np.float32)
        J = ((moved - nominal[None]) / step[:, None, None]).transpose(1, 2, 0)  # (H, W, C)
        J = np.ascontiguousarray(J)
        if delta == self.net.delta:
            self._remember(self._jac, key, (nominal, J))
        return nominal, J
