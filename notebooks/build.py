"""Build the notebooks from their reviewable Python sources: ``src/<name>.py`` -> ``<name>.ipynb``.

The sources use the "percent" cell format (as jupytext, VS Code and Spyder read it)::

    # %% [markdown]
    # # Title
    # text ...

    # %% tags=["parameters"]
    SIZE = 96

    # %%
    print(SIZE)

A markdown cell's lines are comments (the leading ``# `` is removed); ``tags=[...]`` sets the cell's tags (the
test runner injects tiny sizes after the cell tagged ``parameters``, papermill-style).

    python notebooks/build.py            # (re)write every notebook from its source, WITHOUT outputs
    python notebooks/build.py --check    # exit 1 when a committed notebook's cells differ from its source
    python notebooks/build.py --sync-markdown   # copy edited markdown cells into the executed notebooks,
                                                # keeping their outputs (code cells must be unchanged)

Rebuilding drops the outputs: execute the notebook again afterwards (see notebooks/README.md), e.g.
``python -m tests.notebooks.run notebooks/01_depth_modalities.ipynb --inplace``.
"""

from __future__ import annotations

import argparse
import ast
import re
import sys
from pathlib import Path

import nbformat

__all__ = ["NOTEBOOKS", "SRC", "build", "parse_cells", "same_cells", "sync_markdown"]

HERE = Path(__file__).resolve().parent
SRC = HERE / "src"
#: Notebooks built from ``src/<name>.py`` into ``<name>.ipynb``.
NOTEBOOKS = ("01_depth_modalities", "02_code_jacobian", "03_trajectories", "04_textureless")

_HEADER = re.compile(r"^# %%(?P<rest>.*)$")
KERNELSPEC = {"display_name": "Python 3 (ipykernel)", "language": "python", "name": "python3"}


def parse_cells(text: str, name: str = "<source>") -> list[dict]:
    """Split percent-format source into ``[{"type": "code"|"markdown", "source": str, "tags": [...]}]``.

    Raises:
        ValueError: text before the first ``# %%`` marker, or a malformed ``tags=`` list (naming the line).
    """
    cells: list[dict] = []
    cur: dict | None = None
    for lineno, line in enumerate(text.splitlines(), 1):
        m = _HEADER.match(line)
        if m:
            rest = m.group("rest").strip()
            kind = "code"
            if rest.startswith("[markdown]"):
                kind, rest = "markdown", rest[len("[markdown]") :].strip()
            tags: list[str] = []
            if rest:
                if not rest.startswith("tags="):
                    raise ValueError(f"{name}:{lineno}: unknown cell header option {rest!r}")
                try:
                    tags = list(ast.literal_eval(rest[len("tags=") :]))
                except (ValueError, SyntaxError) as e:
                    raise ValueError(f"{name}:{lineno}: bad tags list {rest!r}") from e
            cur = {"type": kind, "lines": [], "tags": tags}
            cells.append(cur)
            continue
        if cur is None:
            if line.strip():
                raise ValueError(f"{name}:{lineno}: text before the first '# %%' cell marker")
            continue
        if cur["type"] == "markdown":
            if line.strip() and not line.startswith("#"):
                raise ValueError(f"{name}:{lineno}: markdown lines must be comments, got {line!r}")
            line = line[2:] if line.startswith("# ") else line[1:]
        cur["lines"].append(line)
    out = []
    for c in cells:
        lines = c["lines"]
        while lines and not lines[-1].strip():
            lines.pop()
        while lines and not lines[0].strip():
            lines.pop(0)
        out.append({"type": c["type"], "source": "\n".join(lines), "tags": c["tags"]})
    return out


def build(src: Path) -> nbformat.NotebookNode:
    """The notebook (no outputs) of a percent-format source file."""
    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = dict(KERNELSPEC)
    nb.metadata["language_info"] = {"name": "python"}
    for c in parse_cells(src.read_text(), str(src)):
        make = nbformat.v4.new_markdown_cell if c["type"] == "markdown" else nbformat.v4.new_code_cell
        cell = make(c["source"])
        if c["tags"]:
            cell.metadata["tags"] = c["tags"]
        nb.cells.append(cell)
    # deterministic cell ids, so that a rebuild of unchanged sources gives the same file
    for i, cell in enumerate(nb.cells):
        cell["id"] = f"cell-{i:02d}"
    nbformat.validate(nb)
    return nb


def same_cells(a: nbformat.NotebookNode, b: nbformat.NotebookNode) -> list[str]:
    """Differences in cell type, source and tags between two notebooks (outputs ignored); [] = same."""
    diffs = []
    if len(a.cells) != len(b.cells):
        diffs.append(f"{len(a.cells)} cells vs {len(b.cells)}")
    for i, (x, y) in enumerate(zip(a.cells, b.cells, strict=False)):
        if x.cell_type != y.cell_type:
            diffs.append(f"cell {i}: {x.cell_type} vs {y.cell_type}")
        elif x.source != y.source:
            diffs.append(f"cell {i}: source differs")
        elif x.metadata.get("tags", []) != y.metadata.get("tags", []):
            diffs.append(f"cell {i}: tags {x.metadata.get('tags', [])} vs {y.metadata.get('tags', [])}")
    return diffs


def sync_markdown(built: nbformat.NotebookNode, executed: nbformat.NotebookNode) -> int:
    """Copy the markdown sources of ``built`` into ``executed`` (outputs kept); returns the cells changed.

    Raises:
        ValueError: the two differ in anything but markdown text (cell count, types, code, tags): re-execute.
    """
    other = [d for d in same_cells(built, executed) if not d.endswith("source differs")]
    code_diff = [
        i
        for i, (x, y) in enumerate(zip(built.cells, executed.cells, strict=False))
        if x.cell_type == "code" and x.source != y.source
    ]
    if other or code_diff:
        raise ValueError(f"not only markdown changed ({other or f'code cells {code_diff}'}): rebuild and execute")
    n = 0
    for x, y in zip(built.cells, executed.cells, strict=True):
        if x.cell_type == "markdown" and x.source != y.source:
            y.source = x.source
            n += 1
    return n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("names", nargs="*", default=list(NOTEBOOKS), help=f"notebooks (default: {NOTEBOOKS})")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--check", action="store_true", help="compare with the committed notebooks, write nothing")
    mode.add_argument(
        "--sync-markdown", action="store_true", help="update only the markdown cells, keeping the outputs"
    )
    a = ap.parse_args(argv)
    bad = 0
    for name in a.names:
        src, dst = SRC / f"{name}.py", HERE / f"{name}.ipynb"
        nb = build(src)
        if a.check:
            if not dst.is_file():
                print(f"{dst}: missing (run python notebooks/build.py)")
                bad += 1
                continue
            diffs = same_cells(nb, nbformat.read(dst, as_version=4))
            if diffs:
                print(f"{dst} is out of date with {src}: " + "; ".join(diffs))
                bad += 1
            else:
                print(f"{dst}: cells match {src}")
        elif a.sync_markdown:
            executed = nbformat.read(dst, as_version=4)
            try:
                n = sync_markdown(nb, executed)
            except ValueError as e:
                print(f"{dst}: {e}")
                bad += 1
                continue
            nbformat.write(executed, dst)
            print(f"{dst}: {n} markdown cell(s) updated, outputs kept")
        else:
            nbformat.write(nb, dst)
            print(f"wrote {dst} (no outputs: execute it, see notebooks/README.md)")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
