"""The notebooks: sources in sync with notebooks/src, committed outputs present, and tiny end-to-end runs.

The end-to-end tests execute every cell of each notebook with nbclient (kernel ``python3`` of this venv) with
tiny sizes injected after the ``parameters`` cell, outputs and caches in ``tmp_path``, one torch thread.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import nbformat
import numpy as np
import pytest

from tests.notebooks.run import REPO, execute_notebook, inject_parameters

NB = REPO / "notebooks"


def _build_module():
    spec = importlib.util.spec_from_file_location("notebooks_build", NB / "build.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _outputs(nb) -> list[dict]:
    return [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]


def _errors(nb) -> list[str]:
    return [f"{o.get('ename')}: {o.get('evalue')}" for o in _outputs(nb) if o.output_type == "error"]


def _env(tmp_path: Path) -> dict:
    return {"DIT_SLAM_CACHE": str(tmp_path / "cache"), "OMP_NUM_THREADS": "1"}


# ------------------------------------------------------------------------------------------------ static
def test_parse_cells_known_answer():
    build = _build_module()
    text = '# %% [markdown]\n# # Title\n#\n# text\n\n# %% tags=["parameters"]\nA = 1\n\n# %%\nprint(A)\n'
    cells = build.parse_cells(text)
    assert cells == [
        {"type": "markdown", "source": "# Title\n\ntext", "tags": []},
        {"type": "code", "source": "A = 1", "tags": ["parameters"]},
        {"type": "code", "source": "print(A)", "tags": []},
    ]
    with pytest.raises(ValueError, match="before the first"):
        build.parse_cells("x = 1\n# %%\n")
    with pytest.raises(ValueError, match="unknown cell header"):
        build.parse_cells("# %% foo\n")


@pytest.mark.parametrize("name", ["01_depth_modalities", "02_code_jacobian", "03_trajectories", "04_textureless"])
def test_committed_notebook_matches_source_and_has_outputs(name):
    build = _build_module()
    committed = nbformat.read(NB / f"{name}.ipynb", as_version=4)
    assert build.same_cells(build.build(NB / "src" / f"{name}.py"), committed) == [], (
        f"run python notebooks/build.py and re-execute {name}.ipynb"
    )
    tagged = [c for c in committed.cells if "parameters" in c.metadata.get("tags", [])]
    assert len(tagged) == 1 and committed.cells.index(tagged[0]) == 1  # one parameter cell, at the top
    code = [c for c in committed.cells if c.cell_type == "code"]
    # the committed copy carries a full run: every code cell executed in order, no errors, figures embedded
    assert [c.execution_count for c in code] == list(range(1, len(code) + 1))
    assert _errors(committed) == []
    assert sum("image/png" in o.get("data", {}) for o in _outputs(committed)) >= 2
    assert not any("injected-parameters" in c.metadata.get("tags", []) for c in committed.cells)


def test_inject_parameters():
    nb = nbformat.v4.new_notebook()
    nb.cells = [
        nbformat.v4.new_markdown_cell("# t"),
        nbformat.v4.new_code_cell("A = 1\nB: int = 2"),
        nbformat.v4.new_code_cell("print(A)"),
    ]
    nb.cells[1].metadata["tags"] = ["parameters"]
    inject_parameters(nb, {"A": 5, "B": "x"})
    assert [c.source for c in nb.cells][2] == "# Parameters injected by tests.notebooks.run\nA = 5\nB = 'x'"
    assert nb.cells[2].metadata["tags"] == ["injected-parameters"] and len(nb.cells) == 4
    inject_parameters(nb, {"A": 6})  # replaces the earlier injection
    assert len(nb.cells) == 4 and nb.cells[2].source.endswith("A = 6")
    with pytest.raises(ValueError, match=r"\['TYPO'\]"):
        inject_parameters(nb, {"TYPO": 1})
    nb.cells[1].metadata["tags"] = []
    with pytest.raises(ValueError, match="exactly one cell tagged 'parameters'"):
        inject_parameters(nb, {})


# ------------------------------------------------------------------------------------------------ end to end
@pytest.mark.slow
def test_01_depth_modalities_tiny(tmp_path):
    out = tmp_path / "out"
    params = {
        "OUT": str(out),
        "VARIANTS": ["dit"],
        "MODALITIES": ["rgb", "grays"],
        "SIZE": 32,
        "WIDTH_MULT": 0.25,
        "STEPS": 2,
        "BATCH": 2,
        "VAL_EVERY": 1,
        "N_TRAIN": 8,
        "N_VAL": 4,
        "THREADS": 1,
        "TIMING_FRAMES": 1,
        "FIG_FRAMES": 2,
        "SEEDS": [0, 1],
    }
    nb = execute_notebook(
        NB / "01_depth_modalities.ipynb", params, tmp_path / "01.ipynb", timeout=300, env=_env(tmp_path)
    )
    assert _errors(nb) == []
    summary = json.loads((out / "ablation_seed0" / "ablation.json").read_text())
    other = json.loads((out / "ablation_seed1" / "ablation.json").read_text())
    assert other["overrides"][-1] == "seed=1" and summary["overrides"][-1] == "seed=0"
    seeds = json.loads((out / "table1_seeds.json").read_text())
    assert seeds["seeds"] == [0, 1] and set(seeds["order"]) == {"rgb_seed0", "rgb_seed1", "grays_seed0", "grays_seed1"}
    for seed, summ in ((0, summary), (1, other)):  # the ratio is the cell's RMSE over its own interpolation row
        c = summ["cells"]["dit_grays"]
        want = c["metrics"]["rmse"] / c["interpolation"]["rmse"]
        assert abs(seeds["rmse_over_interpolation"][f"dit_grays_seed{seed}"] - want) < 1e-12
    assert set(summary["cells"]) == {"dit_rgb", "dit_grays"}
    assert all(c["frames"] == 4 and c["net_config"]["height"] == 32 for c in summary["cells"].values())
    rows = [ln.split(" | ")[0] for ln in summary["table"].splitlines()[2:]]
    assert rows == [
        "| RGB / Ours (DiT)",
        "| RGB / median GT (reference)",
        "| G-S / Ours (DiT)",
        "| G-S / interpolation of the sparse input (reference)",
        "| G-S / median GT (reference)",
    ]
    for png in ("table1_bars.png", "fig7_dit_rgb.png", "fig8_dit_grays.png"):
        assert (out / png).stat().st_size > 1000, png
    shown = [o for o in _outputs(nb) if "image/png" in o.get("data", {})]
    assert len(shown) >= 3  # the figures are displayed inline, not only saved
    if (REPO / "runtime" / "assets" / "default_model" / "manifest.json").is_file():
        res = json.loads((out / "default_model_eval.json").read_text())
        assert res["frames"] == 4 and 0 < res["metrics"]["rmse"] < 5
        assert (out / "fig8_default_model.png").is_file()


@pytest.mark.slow
def test_02_code_jacobian_tiny(tmp_path, standin_64):
    """On the session's 64x64 stand-in (``tests/conftest.py``): its export in the cache is reused, as on a second
    run, and its one synthetic NYU frame is the data."""
    out = tmp_path / "out"
    params = {
        "OUT": str(out),
        "MODEL": "standin",
        "DATA": str(standin_64.data),
        "STANDIN_SIZE": 64,
        "STANDIN_WIDTH_MULT": 0.25,
        "FRAMES": 1,
        "RANDOM_CODES": 0,
        "DELTA_MIN": 1e-3,
        "DELTA_MAX": 1e-1,
        "PER_DECADE": 1,
        "THREADS": 1,
        "RUNS": 1,
        "TORCH_RUNS": 1,
        "SESSION_SWEEP": False,
        "EXACT": False,
    }
    env = dict(_env(tmp_path), DIT_SLAM_CACHE=str(standin_64.cache))
    nb = execute_notebook(NB / "02_code_jacobian.ipynb", params, tmp_path / "02.ipynb", timeout=300, env=env)
    assert _errors(nb) == []
    printed = "".join(o.get("text", "") for o in _outputs(nb) if o.output_type == "stream")
    assert "(reused)" in printed  # the session's export of the stand-in, not a second one
    jac = json.loads((out / "jacobian.json").read_text())
    assert jac["model"]["source"] == "stand-in" and jac["model"]["height"] == 64
    assert jac["deltas"] == pytest.approx([1e-3, 1e-2, 1e-1])
    assert jac["best"]["all_dims"]["delta"] in jac["deltas"]
    # forward differences: the error at delta = 0.1 exceeds the one at 1e-3 (truncation dominates there)
    err = jac["sweep_all_dims"]["mean_abs"]
    assert err[2] > err[0] > 0
    net = json.loads((out / "network.json").read_text())
    assert net["ratios_to_ort_fd"]["ort_fd"] == 1.0
    assert net["comparison"]["accuracy"]["torch_jacfwd"] < 1e-4  # jacfwd == autograd forward mode
    for png in ("jacobian_delta.png", "jacobian_timing.png"):
        assert (out / png).stat().st_size > 1000, png
    assert sum("image/png" in o.get("data", {}) for o in _outputs(nb)) >= 2


@pytest.fixture(scope="module")
def sim_cache(tmp_path_factory):
    """One sequence cache for notebooks 03 and 04 (they share the tiny whitewall sequence)."""
    return tmp_path_factory.mktemp("sim")


@pytest.mark.slow
def test_03_trajectories_tiny(tmp_path, sim_cache):
    from runtime.eval import trajectory_metrics
    from runtime.io.euroc import read_euroc
    from runtime.io.tum import read_tum

    out = tmp_path / "out"
    params = {
        "OUT": str(out),
        "DATA": str(sim_cache),
        "PRESETS": ["textured", "whitewall"],
        "SEEDS": [0],
        "DURATION": 24.0,  # whitewall's minimum
        "SCALE": 0.25,
        "MODES": ["sparse", "dense_eq13", "dense_eq13_14", "dense_gt_eq13_14"],
    }
    nb = execute_notebook(NB / "03_trajectories.ipynb", params, tmp_path / "03.ipynb", timeout=300, env=_env(tmp_path))
    assert _errors(nb) == []
    res = json.loads((out / "table3.json").read_text())
    rows = {(r["preset"], r["mode"]): r for r in res["rows"]}
    assert set(rows) == {(p, m) for p in params["PRESETS"] for m in params["MODES"]}
    for (preset, mode), r in rows.items():
        assert r["seed"] == 0 and r["fps"] > 0 and r["keyframes"] > 5
        # the table's ATE is what the run's trajectory.txt gives against the ground truth (TUM: 9 decimals)
        ts, T = read_tum(out / "runs" / f"{preset}_s0_{mode}" / "trajectory.txt")
        gt = read_euroc(sim_cache / f"euroc_{preset}_24s_s0_x0.25").gt
        assert r["ate"] == pytest.approx(trajectory_metrics(ts, T, gt.ts, gt.T_w_b)["ate_se3_rmse_m"], rel=1e-6)
        dense = mode != "sparse"
        assert np.isfinite(r["rmse_c"]) == dense and (r["decoder_calls"] > 0) == dense
    assert res["dense_configs"]["sparse"] is None
    assert res["dense_configs"]["dense_eq13"]["use_consistency"] is False
    assert res["dense_configs"]["dense_eq13_14"]["use_consistency"] is True
    assert res["dense_configs"]["dense_gt_eq13_14"]["factors"]["sigma_per_b"] == pytest.approx(2**0.5)
    # the rendered depth is the prior there: its c = 0 depth equals the ground truth (interpolation aside)
    assert rows[("textured", "dense_gt_eq13_14")]["rmse_b"] < 1e-3 < rows[("textured", "dense_eq13_14")]["rmse_b"]
    assert "| textured | dense, Eq. 13 + 14 | 1 |" in res["table"]
    assert set(res["bars"]) >= {"textured_dense_eq13_14_minus_sparse", "whitewall_dense_eq13_14_minus_sparse"}
    (coast,) = res["coast"]  # bench_coast on the whitewall runs: the split repeats each run's ATE (same alignment)
    assert set(coast["runs"]) == set(params["MODES"])
    for mode, split in coast["runs"].items():
        assert split["ate"] == pytest.approx(rows[("whitewall", mode)]["ate"], rel=1e-6)
    assert coast["+ wall distance per axis"][0] <= coast["end pose+vel per axis"][0]
    for png in ("table3_ate.png", "fig10_trajectories.png"):
        assert (out / png).stat().st_size > 1000, png
    assert sum("image/png" in o.get("data", {}) for o in _outputs(nb)) >= 2


@pytest.mark.slow
def test_04_textureless_tiny(tmp_path, sim_cache):
    out = tmp_path / "out"
    params = {"OUT": str(out), "DATA": str(sim_cache), "DURATION": 24.0, "SCALE": 0.25, "VIEW_SIZE": (160, 100)}
    nb = execute_notebook(NB / "04_textureless.ipynb", params, tmp_path / "04.ipynb", timeout=300, env=_env(tmp_path))
    assert _errors(nb) == []
    res = json.loads((out / "textureless.json").read_text())
    info = json.loads((sim_cache / "euroc_whitewall_24s_s0_x0.25" / "sim_info.json").read_text())
    assert res["stop_s"] == info["whitewall_window_s"][1]  # the runs stop at the end of the hold
    assert res["frames"] == int(round(res["stop_s"] * 20)) + 1
    assert res["dense"]["dense_map_points"] > 100 and res["sparse"]["keyframes"] > 5
    fig4 = res["fig4"]
    assert {"textured", "white wall"} <= set(fig4)
    n_consis = res["dense_config"]["n_consis"]
    for f in fig4.values():
        assert sum(f["n_per_cell"]) == n_consis and sum(f["gamma"]) == pytest.approx(1.0)
        c, n = np.array(f["counts"]), np.array(f["n_per_cell"])
        if c.sum():  # a cell with the most features gets the fewest samples (equal counts may round apart)
            assert n[c == c.max()].min() == n.min(), (c.tolist(), n.tolist())
    assert sum(fig4["white wall"]["counts"]) < sum(fig4["textured"]["counts"])
    for png in ("fig11_maps.png", "fig4_sampling.png"):
        assert (out / png).stat().st_size > 1000, png
    assert sum("image/png" in o.get("data", {}) for o in _outputs(nb)) >= 2
