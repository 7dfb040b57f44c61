"""Write the notebooks of this folder from their sources in ``notebooks/src/``.

Each source is a plain Python script in the "percent" format: ``# %%`` starts a code
cell, ``# %% [markdown]`` a markdown cell whose lines are comments (``# `` stripped).
A source runs as a script too, which is handy while editing it:
``.venv/bin/python notebooks/src/01_verify_the_theorems.py``.  After editing, run
``.venv/bin/python notebooks/_build.py`` and commit the ``.ipynb`` files (written
without outputs); ``tests/test_notebooks.py`` executes every notebook top to bottom and
checks that a rebuild would leave the committed notebooks' content unchanged (cell
types, ids, sources, metadata; compared as parsed JSON, so a newer nbformat that lays the
file out differently does not count as a change).

The build is deterministic: cell ids (nbformat 4.5 requires one per cell, and
``nbformat.v4.new_*_cell`` draws a random one) are set to ``<notebook name>-<cell index>``
(:func:`cell_id`), so rebuilding an unchanged source rewrites nothing.
"""

import glob
import os
import re
import sys

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = os.path.dirname(os.path.abspath(__file__))


def cells(text):
    """``[(kind, source), ...]`` of a percent-format script."""
    out, kind, lines = [], None, []

    def flush():
        src = "\n".join(lines).strip("\n")
        if kind is not None and src:
            out.append((kind, src))

    for line in text.splitlines():
        if line.startswith("# %%"):
            flush()
            kind, lines = ("md" if "[markdown]" in line else "code"), []
        elif kind == "md":
            lines.append(line[2:] if line.startswith("# ") else line.lstrip("#"))
        elif kind == "code":
            lines.append(line)
    flush()
    return out


def cell_id(stem, index):
    """Id of cell ``index`` of notebook ``stem``: ``"<stem>-<index:02d>"``, with characters
    outside nbformat's ``[a-zA-Z0-9-_]`` replaced by ``-`` and the stem shortened to keep
    the id within nbformat's 64 characters."""
    suffix = f"-{index:02d}"
    base = re.sub(r"[^a-zA-Z0-9_-]", "-", stem)[:64 - len(suffix)] or "cell"
    return base + suffix


def build(text, name="notebook"):
    """The notebook (no outputs) of percent-format source ``text``; ``name`` (the notebook's
    file name without extension) seeds the cell ids."""
    nb = new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3",
                                 "language": "python"}
    nb.metadata["language_info"] = {"name": "python"}
    for i, (kind, src) in enumerate(cells(text)):
        new = new_markdown_cell if kind == "md" else new_code_cell
        nb.cells.append(new(src, id=cell_id(name, i)))
    nbformat.validate(nb)
    return nb


def notebook_text(nb):
    """The file contents written for ``nb`` (nbformat's JSON, ending in a newline)."""
    text = nbformat.writes(nb)
    return text if text.endswith("\n") else text + "\n"


def main(names=(), out_dir=HERE, quiet=False):
    """Build every source in ``src/`` (or only ``names``) into ``out_dir``; returns the
    paths written."""
    written = []
    for path in sorted(glob.glob(os.path.join(HERE, "src", "*.py"))):
        stem = os.path.basename(path)[:-3]
        name = stem + ".ipynb"
        if names and name not in names and os.path.basename(path) not in names:
            continue
        with open(path, encoding="utf-8") as f:
            nb = build(f.read(), stem)
        out = os.path.join(out_dir, name)
        with open(out, "w", encoding="utf-8", newline="\n") as f:
            f.write(notebook_text(nb))
        written.append(out)
        if not quiet:
            print("wrote", name, f"({len(nb.cells)} cells)")
    return written


if __name__ == "__main__":
    main(sys.argv[1:])
