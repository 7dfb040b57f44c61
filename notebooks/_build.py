"""Write the notebooks of this folder from their sources in ``notebooks/src/``.

Each source is a plain Python script in the "percent" format: ``# %%`` starts a code
cell, ``# %% [markdown]`` a markdown cell whose lines are comments (``# `` stripped).
A source runs as a script too, which is handy while editing it:
``.venv/bin/python notebooks/src/01_verify_the_theorems.py``.  After editing, run
``.venv/bin/python notebooks/_build.py`` and commit the ``.ipynb`` files (written
without outputs); ``tests/test_notebooks.py`` executes every notebook top to bottom.
"""

import glob
import os
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


def build(text):
    nb = new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3",
                                 "language": "python"}
    nb.metadata["language_info"] = {"name": "python"}
    for kind, src in cells(text):
        nb.cells.append(new_markdown_cell(src) if kind == "md" else new_code_cell(src))
    nbformat.validate(nb)
    return nb


def main(names=()):
    for path in sorted(glob.glob(os.path.join(HERE, "src", "*.py"))):
        name = os.path.basename(path)[:-3] + ".ipynb"
        if names and name not in names and os.path.basename(path) not in names:
            continue
        with open(path, encoding="utf-8") as f:
            nb = build(f.read())
        nbformat.write(nb, os.path.join(HERE, name))
        print("wrote", name, f"({len(nb.cells)} cells)")


if __name__ == "__main__":
    main(sys.argv[1:])
