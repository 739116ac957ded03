"""torch -> ONNX for the depth network: ``prior.onnx``, ``decoder.onnx`` and ``manifest.json``.

The exported modules are tensors in, tensors out (STYLE.md "Export"):

* ``prior.onnx``: ``image`` [1, Cin, H, W] (image channels in [0, 1], then the sparse depth channel in metres for the
  ``*s`` modalities) -> ``uncertainty`` [1, 1, H, W] (metres) and the conditioning features ``feat0 .. featN``.
  A relative network also takes ``fill`` [1, 1, H, W] (metres): the interpolated sparse channel,
  ``runtime.densify.interpolate_sparse``, computed outside the graph.
* ``decoder.onnx``: ``code`` [B, C] + ``feat0 .. featN`` (batch 1, broadcast inside) -> ``depth`` [B, 1, H, W] (metres).
  The batch is symbolic: the runtime sends 1 code, or 8 perturbed codes for the finite-difference Jacobian (Eq. 17).

The export is written into a hidden temporary folder beside ``out_dir`` and renamed into place only when both
graphs passed the checks, so an interrupted export never leaves a mixed model. ``manifest.json`` records each
ONNX file's SHA-256 and a run id, which :class:`runtime.network.DepthNetwork` verifies at load.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import torch
from torch import nn

log = logging.getLogger(__name__)

MANIFEST_VERSION = 2  # 2: file hashes and run id
EXPORT_FILES = ("prior.onnx", "decoder.onnx", "manifest.json")
PARITY_TOLERANCE_M = 1e-4
DEFAULT_DELTA = 1e-2


class PriorGraph(nn.Module):
    """``image [, fill] -> (uncertainty, *features)``: the part that runs once per keyframe."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor, fill: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        uncertainty, features = self.net.prior(image) if fill is None else self.net.prior(image, fill)
        return (uncertainty, *features)


def prior_inputs(net: nn.Module, image: torch.Tensor) -> dict[str, torch.Tensor]:
    """The prior graph's inputs for ``image``: ``image``, plus ``fill`` for a relative network."""
    if not getattr(net, "relative", False):
        return {"image": image}
    from models.blocks import linear_fill

    return {"image": image, "fill": linear_fill(image[:, -1:])}


class DecoderGraph(nn.Module):
    """``(code, feat0 .. feat5) -> depth``: the part that runs whenever a depth code changes.

    The arguments are spelled out (no ``*features``): ``torch.export`` cannot pair a varargs tuple with
    ``dynamic_shapes`` for the symbolic code batch.
    """

    N_FEATURES = 6

    def __init__(self, net: nn.Module):
        super().__init__()
        self.decoder = net.decoder

    def forward(self, code, feat0, feat1, feat2, feat3, feat4, feat5) -> torch.Tensor:
        return self.decoder(code, feat0, feat1, feat2, feat3, feat4, feat5)


def git_sha() -> str | None:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            cwd=Path(__file__).resolve().parent,
        )
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def _export(module: nn.Module, args: tuple, path: Path, input_names, output_names, dynamic_shapes, opset: int):
    torch.onnx.export(
        module,
        args,
        str(path),
        input_names=list(input_names),
        output_names=list(output_names),
        dynamic_shapes=dynamic_shapes,
        opset_version=opset,
        external_data=False,
        dynamo=True,
        verbose=False,
    )


def _io_spec(session_io) -> list[dict]:
    return [
        {"name": x.name, "shape": [d if isinstance(d, int) else str(d) for d in x.shape], "type": x.type}
        for x in session_io
    ]


def example_inputs(in_channels: int, height: int, width: int, n: int, seed: int = 0) -> list[torch.Tensor]:
    """``n`` plausible network inputs [1, Cin, H, W]: smooth random images and a sparse depth channel."""
    g = torch.Generator().manual_seed(seed)
    out = []
    has_sparse = in_channels in (2, 4)
    n_img = in_channels - 1 if has_sparse else in_channels
    for _ in range(n):
        img = torch.rand(1, n_img, height // 8, width // 8, generator=g)
        img = nn.functional.interpolate(img, size=(height, width), mode="bilinear", align_corners=False)
        chans = [img]
        if has_sparse:
            mask = torch.rand(1, 1, height, width, generator=g) < 125.0 / (height * width)
            depth = 0.5 + 6.0 * torch.rand(1, 1, height, width, generator=g)
            chans.append(depth * mask)
        out.append(torch.cat(chans, 1))
    return out


def parity_check(
    net: nn.Module,
    prior_path: Path,
    decoder_path: Path,
    inputs: list[torch.Tensor],
    code_dim: int,
    seed: int = 0,
) -> dict:
    """Compare ONNX Runtime with torch on ``inputs`` at decoder batches 1 and 8; return the figures."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    prior = ort.InferenceSession(str(prior_path), so, providers=["CPUExecutionProvider"])
    decoder = ort.InferenceSession(str(decoder_path), so, providers=["CPUExecutionProvider"])
    g = torch.Generator().manual_seed(seed)
    max_depth, max_unc, max_feat = 0.0, 0.0, 0.0
    with torch.no_grad():
        for image in inputs:
            feed_t = prior_inputs(net, image)
            unc_t, feats_t = net.prior(*feed_t.values())
            outs = prior.run(None, {k: v.numpy() for k, v in feed_t.items()})
            max_unc = max(max_unc, float(np.abs(outs[0] - unc_t.numpy()).max()))
            for a, b in zip(outs[1:], feats_t, strict=True):
                max_feat = max(max_feat, float(np.abs(a - b.numpy()).max()))
            feed = {f"feat{i}": f for i, f in enumerate(outs[1:])}
            for batch in (1, 8):
                code = torch.randn(batch, code_dim, generator=g)
                depth_t = net.decoder(code, *feats_t).numpy()
                depth_o = decoder.run(None, {"code": code.numpy(), **feed})[0]
                max_depth = max(max_depth, float(np.abs(depth_o - depth_t).max()))
    return {
        "inputs": len(inputs),
        "decoder_batches": [1, 8],
        "max_abs_depth_m": max_depth,
        "max_abs_uncertainty_m": max_unc,
        "max_abs_feature": max_feat,
        "tolerance_m": PARITY_TOLERANCE_M,
    }


def export_network(
    net: nn.Module,
    out_dir: str | Path,
    *,
    modality: str,
    height: int,
    width: int,
    opset: int = 18,
    delta: float = DEFAULT_DELTA,
    n_parity: int = 4,
    parity_inputs: list[torch.Tensor] | None = None,
    train_config: dict | None = None,
    source: str | None = None,
    extra: dict | None = None,
) -> dict:
    """Export ``net`` (a CVAE model with ``prior`` and ``decoder``) and write the manifest.

    Raises:
        ValueError: the net has no code (``fastdepth``) or the sizes are not multiples of 32.
        RuntimeError: ``onnx.checker`` rejects a graph or the parity exceeds ``PARITY_TOLERANCE_M``.
        FileExistsError: ``out_dir`` is a file or holds files that are not an earlier export.
    """
    if not hasattr(net, "decoder") or not hasattr(net, "prior"):
        raise ValueError(f"{type(net).__name__} has no depth code (prior/decoder): only CVAE models export")
    if height % 32 or width % 32:
        raise ValueError(f"network size {height}x{width} is not a multiple of 32")
    from runtime.network import file_sha256
    from runtime.outputs import new_run_id

    out_final = Path(out_dir)
    _check_out(out_final)
    run_id = new_run_id()
    stage = out_final.parent / f".{out_final.name}.partial-{run_id}"
    stage.mkdir(parents=True)
    try:
        manifest = _export_into(
            net.eval().float(), stage, modality, height, width, opset, delta, n_parity, parity_inputs, source
        )
        manifest.update(run_id=run_id, train_config=train_config)
        if extra:
            manifest.update(extra)
        manifest["files"] = {
            p.name: {"sha256": file_sha256(p), "bytes": p.stat().st_size}
            for p in (stage / "prior.onnx", stage / "decoder.onnx")
        }
        (stage / "manifest.json").write_text(json.dumps(manifest, indent=2))
        _swap_into_place(stage, out_final)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return manifest


def _check_out(out: Path) -> None:
    """``out`` may be new, empty or an earlier export (its other files are kept); anything else is refused."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"out={out} is a file, not a folder")
    if not out.is_dir() or not any(not p.name.startswith(".") for p in out.iterdir()):
        return  # new, or empty but for hidden entries (Hydra's .export/ log folder)
    try:
        ours = json.loads((out / "manifest.json").read_text()).get("format") == "dit-slam-depth-network"
    except (OSError, ValueError, AttributeError):
        ours = False
    if not ours:
        raise FileExistsError(f"out={out} holds files that dit-export did not write (no manifest.json); choose another")


def _swap_into_place(stage: Path, out: Path) -> None:
    """Rename the finished ``stage`` folder to ``out``; an earlier export there is replaced as a whole (its other
    files, e.g. a README, are moved into the new folder first). A reader sees the old model, the new one, or
    briefly none, never a mix."""
    if out.is_dir():
        for p in out.iterdir():
            if p.name not in EXPORT_FILES and not (stage / p.name).exists():
                os.replace(p, stage / p.name)
        old = out.parent / f".{out.name}.old-{stage.name.rsplit('partial-', 1)[-1]}"
        os.replace(out, old)
        os.replace(stage, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        os.replace(stage, out)


def _export_into(net, out_dir: Path, modality, height, width, opset, delta, n_parity, parity_inputs, source) -> dict:
    """The two graphs, their checks and the manifest (without hashes) in ``out_dir``."""
    import onnx
    import onnxruntime as ort

    in_channels = int(net.in_channels)
    code_dim = int(net.code_dim)
    image = example_inputs(in_channels, height, width, 1, seed=123)[0]
    feed = prior_inputs(net, image)
    with torch.no_grad():
        _, feats = net.prior(*feed.values())
    n_feat = len(feats)
    if n_feat != DecoderGraph.N_FEATURES:
        raise ValueError(f"the decoder takes {n_feat} features; the exporter handles {DecoderGraph.N_FEATURES}")
    feat_names = [f"feat{i}" for i in range(n_feat)]

    prior_path, decoder_path = out_dir / "prior.onnx", out_dir / "decoder.onnx"
    _export(
        PriorGraph(net).eval(), tuple(feed.values()), prior_path, list(feed), ["uncertainty", *feat_names], None, opset
    )
    batch = torch.export.Dim("batch", min=1, max=256)
    codes = torch.zeros(8, code_dim)  # traced at B = 8, the Jacobian batch
    _export(
        DecoderGraph(net).eval(),
        (codes, *feats),
        decoder_path,
        ["code", *feat_names],
        ["depth"],
        {"code": {0: batch}, **{name: None for name in feat_names}},
        opset,
    )

    opsets = {}
    for p in (prior_path, decoder_path):
        model = onnx.load(str(p))
        try:
            onnx.checker.check_model(model, full_check=True)
        except onnx.checker.ValidationError as e:
            raise RuntimeError(f"onnx.checker rejected {p}: {e}") from e
        opsets[p.name] = max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))

    inputs = parity_inputs if parity_inputs is not None else example_inputs(in_channels, height, width, n_parity)
    parity = parity_check(net, prior_path, decoder_path, inputs, code_dim)
    log.info("parity: max |depth_onnx - depth_torch| = %.3g m", parity["max_abs_depth_m"])
    if not parity["max_abs_depth_m"] <= PARITY_TOLERANCE_M:
        raise RuntimeError(
            f"ONNX Runtime and torch disagree: max abs depth difference {parity['max_abs_depth_m']:.3g} m "
            f"> {PARITY_TOLERANCE_M:g} m ({out_dir})"
        )

    describe = net.describe() if hasattr(net, "describe") else {}
    prior_s = ort.InferenceSession(str(prior_path), providers=["CPUExecutionProvider"])
    decoder_s = ort.InferenceSession(str(decoder_path), providers=["CPUExecutionProvider"])
    manifest = {
        "format": "dit-slam-depth-network",
        "version": MANIFEST_VERSION,
        "model": describe.get("model", type(net).__name__),
        "modality": modality,
        "in_channels": in_channels,
        "height": height,
        "width": width,
        "code_dim": code_dim,
        "input_normalization": describe.get("input"),
        "depth_parametrization": describe.get("depth"),
        "depth_unit": "m",
        "jacobian": {"method": "forward finite differences (Eq. 17)", "delta": delta, "batch": code_dim},
        "prior": {
            "file": prior_path.name,
            "opset": opsets[prior_path.name],
            "inputs": _io_spec(prior_s.get_inputs()),
            "outputs": _io_spec(prior_s.get_outputs()),
        },
        "decoder": {
            "file": decoder_path.name,
            "opset": opsets[decoder_path.name],
            "inputs": _io_spec(decoder_s.get_inputs()),
            "outputs": _io_spec(decoder_s.get_outputs()),
        },
        "parity": parity,
        "network": describe,
        "source": source,
        "git_sha": git_sha(),
        "torch_version": torch.__version__,
        "onnxruntime_version": ort.__version__,
    }
    return manifest
