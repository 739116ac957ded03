"""Execute notebooks with nbclient, optionally with parameters injected papermill-style.

    python -m tests.notebooks.run notebooks/01_depth_modalities.ipynb --inplace     # the committed full run
    python -m tests.notebooks.run notebooks/02_code_jacobian.ipynb -o /tmp/02.ipynb -p FRAMES=1 -p THREADS=1

Parameters (``-p NAME=VALUE``, the value read as a Python literal, else as a string) go into a new cell tagged
``injected-parameters`` right after the cell tagged ``parameters``, so that they override its defaults (as
papermill does). The kernel is ``python3`` (the interpreter running this module, i.e. the venv), started in
the repository root with ``OMP_WAIT_POLICY=PASSIVE`` (the code comes from the installed packages); a cell error
stops the run and is reported with the cell's number (the partly executed notebook is still written).
"""

from __future__ import annotations

import argparse
import ast
import os
import sys
import time
from pathlib import Path

import nbformat

__all__ = ["REPO", "inject_parameters", "execute_notebook", "main"]

REPO = Path(__file__).resolve().parents[2]


def inject_parameters(nb: nbformat.NotebookNode, params: dict) -> nbformat.NotebookNode:
    """Insert ``NAME = repr(value)`` lines in a cell tagged ``injected-parameters`` after the parameter cell.

    An earlier injected cell is replaced. Raises ``ValueError`` when no cell is tagged ``parameters``, or when
    a name is not assigned in that cell (a typo would otherwise be silently ignored).
    """
    idx = [i for i, c in enumerate(nb.cells) if "parameters" in c.metadata.get("tags", [])]
    if len(idx) != 1:
        raise ValueError(f"need exactly one cell tagged 'parameters', found {len(idx)}")
    nb.cells = [c for c in nb.cells if "injected-parameters" not in c.metadata.get("tags", [])]
    i = idx[0]
    known = set()
    for node in ast.walk(ast.parse(nb.cells[i].source)):
        if isinstance(node, ast.Assign):
            known |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            known.add(node.target.id)
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(f"parameters {unknown} are not set in the parameters cell (known: {sorted(known)})")
    if params:
        src = "# Parameters injected by tests.notebooks.run\n" + "\n".join(f"{k} = {v!r}" for k, v in params.items())
        cell = nbformat.v4.new_code_cell(src)
        cell.metadata["tags"] = ["injected-parameters"]
        cell["id"] = "injected-parameters"
        nb.cells.insert(i + 1, cell)
    return nb


def kernel_env(extra: dict | None = None) -> dict:
    env = dict(os.environ)
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    env["MPLBACKEND"] = "module://matplotlib_inline.backend_inline"  # figures shown inline AND saved
    env.update(extra or {})
    return env


def execute_notebook(
    path: str | Path,
    params: dict | None = None,
    output: str | Path | None = None,
    timeout: int = 3600,
    cwd: str | Path = REPO,
    env: dict | None = None,
) -> nbformat.NotebookNode:
    """Execute a notebook (every cell, in order) and write it with its outputs to ``output`` (if given).

    Args:
        path: the ``.ipynb`` file.
        params: parameter overrides (see :func:`inject_parameters`).
        output: where to write the executed notebook (may be ``path`` itself).
        timeout: seconds allowed per cell.
        cwd: the kernel's working directory.
        env: extra environment variables of the kernel.

    Raises:
        nbclient.exceptions.CellExecutionError: a cell raised (the notebook is written first).
    """
    from nbclient import NotebookClient
    from nbclient.exceptions import CellExecutionError

    path = Path(path)
    nb = nbformat.read(path, as_version=4)
    inject_parameters(nb, dict(params or {}))
    client = NotebookClient(
        nb,
        timeout=timeout,
        kernel_name="python3",
        resources={"metadata": {"path": str(cwd)}},
        record_timing=False,
    )
    try:
        client.execute(env=kernel_env(env))
    except CellExecutionError:
        if output is not None:
            nbformat.write(nb, str(output))
        raise
    if output is not None:
        nbformat.write(nb, str(output))
    return nb


def _literal(text: str):
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("notebooks", nargs="+", type=Path)
    dest = ap.add_mutually_exclusive_group()
    dest.add_argument("--inplace", action="store_true", help="write the outputs into the notebook itself")
    dest.add_argument("-o", "--output", type=Path, help="output notebook (one input notebook only)")
    ap.add_argument("-p", "--param", action="append", default=[], metavar="NAME=VALUE", help="parameter override")
    ap.add_argument("--timeout", type=int, default=3600, help="seconds per cell (default 3600)")
    a = ap.parse_args(argv)
    if a.output and len(a.notebooks) > 1:
        ap.error("--output takes one notebook")
    params = {}
    for p in a.param:
        if "=" not in p:
            ap.error(f"-p {p!r}: expected NAME=VALUE")
        k, v = p.split("=", 1)
        params[k.strip()] = _literal(v)
    from nbclient.exceptions import CellExecutionError

    for nb_path in a.notebooks:
        out = nb_path if a.inplace else a.output
        t0 = time.perf_counter()
        print(f"executing {nb_path} ...", flush=True)
        try:
            execute_notebook(nb_path, params, out, timeout=a.timeout)
        except (CellExecutionError, ValueError) as e:
            print(f"{nb_path}: FAILED\n{e}", file=sys.stderr)
            return 1
        print(f"{nb_path}: done in {time.perf_counter() - t0:.0f} s" + (f", wrote {out}" if out else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
