"""Tiny hand-built depth models (ONNX graphs of a few nodes) in the dit-export folder layout, and a tiny sequence.

The graphs have the exported network's interface (``image`` -> ``uncertainty`` + ``feat0..feat5``; ``code`` +
features -> ``depth``) so :class:`runtime.network.DepthNetwork` loads them, without torch or an export.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

N_FEAT = 6


def fail_on_call(real, n: int, calls: list, error: BaseException | type = KeyboardInterrupt):
    """``real`` wrapped to fail on its ``n``-th call: every call appends its first argument to ``calls``, the
    ``n``-th raises ``error`` (Ctrl-C by default) instead of calling ``real``."""

    def wrapped(*args, **kwargs):
        calls.append(args[0] if args else None)
        if len(calls) == n:
            raise error
        return real(*args, **kwargs)

    return wrapped


def _prior(channels: int, h: int, w: int, bias: float):
    from onnx import TensorProto, helper

    nodes = [helper.make_node("ReduceMean", ["image", "axes"], ["mean"], keepdims=1)]
    nodes.append(helper.make_node("Add", ["mean", "bias"], ["uncertainty"]))
    outs = [helper.make_tensor_value_info("uncertainty", TensorProto.FLOAT, [1, 1, h, w])]
    for i in range(N_FEAT):
        nodes.append(helper.make_node("Identity", ["mean"], [f"feat{i}"]))
        outs.append(helper.make_tensor_value_info(f"feat{i}", TensorProto.FLOAT, [1, 1, h, w]))
    graph = helper.make_graph(
        nodes,
        "prior",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, channels, h, w])],
        outs,
        [
            helper.make_tensor("axes", TensorProto.INT64, [1], [1]),
            helper.make_tensor("bias", TensorProto.FLOAT, [], [bias]),
        ],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)


def _decoder(h: int, w: int, code_dim: int):
    from onnx import TensorProto, helper

    nodes = [
        helper.make_node("ReduceSum", ["code", "one"], ["s"], keepdims=1),  # (B, 1)
        helper.make_node("Reshape", ["s", "shape"], ["s4"]),  # (B, 1, 1, 1)
        helper.make_node("Add", ["feat0", "s4"], ["d"]),
        helper.make_node("Add", ["d", "two"], ["depth"]),
    ]
    ins = [helper.make_tensor_value_info("code", TensorProto.FLOAT, ["batch", code_dim])]
    ins += [helper.make_tensor_value_info(f"feat{i}", TensorProto.FLOAT, [1, 1, h, w]) for i in range(N_FEAT)]
    graph = helper.make_graph(
        nodes,
        "decoder",
        ins,
        [helper.make_tensor_value_info("depth", TensorProto.FLOAT, ["batch", 1, h, w])],
        [
            helper.make_tensor("one", TensorProto.INT64, [1], [1]),
            helper.make_tensor("shape", TensorProto.INT64, [4], [-1, 1, 1, 1]),
            helper.make_tensor("two", TensorProto.FLOAT, [], [2.0]),
        ],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)


def _spec(session_io) -> list[dict]:
    return [{"name": x.name, "shape": [d if isinstance(d, int) else str(d) for d in x.shape]} for x in session_io]


def write_model(
    out: Path, modality: str = "grays", h: int = 64, w: int = 96, bias: float = 0.1, hashes: bool = True
) -> Path:
    """A model folder (prior.onnx, decoder.onnx, manifest.json) like dit-export's; ``bias`` changes the prior's
    bytes (two folders with different ``bias`` are two different exports)."""
    import hashlib

    import onnx
    import onnxruntime as ort

    from runtime.network import MODALITY_CHANNELS

    def file_sha256(p):
        return hashlib.sha256(Path(p).read_bytes()).hexdigest()

    out.mkdir(parents=True, exist_ok=True)
    code_dim = 8
    onnx.save(_prior(MODALITY_CHANNELS[modality], h, w, bias), str(out / "prior.onnx"))
    onnx.save(_decoder(h, w, code_dim), str(out / "decoder.onnx"))
    p = ort.InferenceSession(str(out / "prior.onnx"), providers=["CPUExecutionProvider"])
    d = ort.InferenceSession(str(out / "decoder.onnx"), providers=["CPUExecutionProvider"])
    manifest = {
        "format": "dit-slam-depth-network",
        "version": 2,
        "modality": modality,
        "in_channels": MODALITY_CHANNELS[modality],
        "height": h,
        "width": w,
        "code_dim": code_dim,
        "jacobian": {"delta": 0.01},
        "prior": {"file": "prior.onnx", "inputs": _spec(p.get_inputs()), "outputs": _spec(p.get_outputs())},
        "decoder": {"file": "decoder.onnx", "inputs": _spec(d.get_inputs()), "outputs": _spec(d.get_outputs())},
        "run_id": f"fake-{bias}",
    }
    if hashes:
        manifest["files"] = {n: {"sha256": file_sha256(out / n)} for n in ("prior.onnx", "decoder.onnx")}
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return out


def circle_trajectory(n: int = 141, rate_hz: float = 20.0, t0_ns: int = 10**18):
    """``n`` body poses on a 2 m circle at ``rate_hz`` (timestamps in ns), yaw following the path."""
    t = np.arange(n) / rate_hz
    a = 0.4 * t
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = 2 * np.cos(a), 2 * np.sin(a), 0.3 * np.sin(1.3 * t)
    c, s = np.cos(a + np.pi / 2), np.sin(a + np.pi / 2)
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -s, s, c
    return t0_ns + np.round(t * 1e9).astype(np.int64), T
