"""The notebooks in notebooks/ run top to bottom without an error, and match their sources
(a rebuild with notebooks/_build.py would change no cell type, source, id or metadata, no
output, and no notebook metadata).

Each notebook is executed by nbclient in a fresh ``python3`` kernel of this interpreter
(ipykernel is in the ``test`` extra; jupyter_client launches the kernel with
``sys.executable``), with notebooks/ as the working directory.  Marked ``slow`` (one to two
minutes in all with numba's cache warm; deselect with ``-m "not slow"``); the Mitsuba notebook is also marked
``mitsuba``.
"""

from __future__ import annotations

import glob
import importlib.util
import json
import os
import time

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NB_DIR = os.path.join(ROOT, "notebooks")
NOTEBOOKS = sorted(glob.glob(os.path.join(NB_DIR, "*.ipynb")))
#: Seconds allowed for one cell (the slowest takes ~20 s on 2 busy cores).
CELL_TIMEOUT = 300
NEEDS_MITSUBA = {"02_classical_reconstruction.ipynb"}


def _param(path):
    name = os.path.basename(path)
    marks = [pytest.mark.slow] + ([pytest.mark.mitsuba] if name in NEEDS_MITSUBA else [])
    return pytest.param(path, id=name, marks=marks)


def test_the_three_notebooks_exist():
    names = [os.path.basename(p) for p in NOTEBOOKS]
    assert names == ["01_verify_the_theorems.ipynb", "02_classical_reconstruction.ipynb",
                     "03_learned_weights.ipynb"], names


def _builder():
    spec = importlib.util.spec_from_file_location("_nb_build", os.path.join(NB_DIR, "_build.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("path", NOTEBOOKS, ids=os.path.basename)
def test_notebook_matches_its_source(path):
    """The committed .ipynb holds the cells of notebooks/src/<name>.py (rebuild with
    ``.venv/bin/python notebooks/_build.py`` after editing a source)."""
    src = os.path.join(NB_DIR, "src", os.path.basename(path)[:-6] + ".py")
    with open(src, encoding="utf-8") as f:
        want = [(c.cell_type, c.source) for c in _builder().build(f.read()).cells]
    got = [(c.cell_type, c.source) for c in nbformat.read(path, as_version=4).cells]
    assert got == want, f"{os.path.basename(path)} is out of date: run notebooks/_build.py"


def _content(text):
    """What a rebuild must keep of a notebook file's JSON: the notebook metadata and each
    cell's type, id, source, metadata (and a code cell's outputs and execution count).
    Not the layout (indentation, key order, a source as one string or a list of lines,
    nbformat_minor), which the unpinned nbformat may write differently."""
    nb = json.loads(text)

    def src(s):
        return "".join(s) if isinstance(s, list) else s

    return {"metadata": nb.get("metadata"),
            "cells": [{"cell_type": c.get("cell_type"), "id": c.get("id"),
                       "source": src(c.get("source", "")), "metadata": c.get("metadata"),
                       "outputs": c.get("outputs"), "execution_count": c.get("execution_count")}
                      for c in nb.get("cells", [])]}


def test_content_ignores_layout_but_not_ids_or_sources():
    """The comparison of test_rebuild_changes_nothing: blind to how nbformat lays out the
    JSON, not to what the notebook holds."""
    cell = {"cell_type": "code", "id": "a-00", "metadata": {}, "source": ["x = 1\n", "y"],
            "outputs": [], "execution_count": None}
    nb = {"cells": [cell], "metadata": {"kernelspec": {"name": "python3"}},
          "nbformat": 4, "nbformat_minor": 5}
    base = _content(json.dumps(nb, indent=1))
    relaid = dict(nb, nbformat_minor=6, cells=[dict(cell, source="x = 1\ny")])
    assert _content(json.dumps(relaid, indent=2, sort_keys=True)) == base
    for change in ({"id": "a-01"}, {"source": "x = 2\ny"}, {"cell_type": "markdown"},
                   {"metadata": {"tags": ["t"]}}, {"execution_count": 1},
                   {"outputs": [{"output_type": "stream", "name": "stdout", "text": "x"}]}):
        assert _content(json.dumps(dict(nb, cells=[dict(cell, **change)]))) != base, change
    assert _content(json.dumps(dict(nb, metadata={}))) != base


def test_rebuild_changes_nothing(tmp_path):
    """Regression (fresh-clone trial): nbformat gave every cell a random id, so running
    notebooks/_build.py in a clean clone rewrote all three notebooks (49 lines, ids only).
    Build (without executing) into a temporary folder, twice: the two builds must agree
    byte for byte, and each is compared with the committed files on what the notebook holds (:func:`_content`: cells' type, id, source,
    metadata and outputs; the notebook metadata), not bytes: the JSON layout is nbformat's
    (not pinned), so a new nbformat that writes it differently does not fail this test,
    while a build that changes an id or a source does."""
    build = _builder()
    first = build.main(out_dir=str(tmp_path), quiet=True)
    assert sorted(os.path.basename(p) for p in first) == [os.path.basename(p) for p in NOTEBOOKS]
    again = tmp_path / "again"
    again.mkdir()
    build.main(out_dir=str(again), quiet=True)
    for path in first:
        name = os.path.basename(path)
        with open(path, encoding="utf-8") as f:
            built_text = f.read()
        built = _content(built_text)
        with open(again / name, encoding="utf-8") as f:
            # one nbformat, one process: two builds must agree byte for byte
            assert f.read() == built_text, (f"two builds of {name} differ: the build is "
                                            "not deterministic")
        with open(os.path.join(NB_DIR, name), encoding="utf-8") as f:
            committed = _content(f.read())
        assert built == committed, (f"notebooks/{name} differs from a fresh build: run "
                                    ".venv/bin/python notebooks/_build.py and commit it")
        nb = nbformat.reads(built_text, as_version=4)
        nbformat.validate(nb)
        ids = [c.id for c in nb.cells]
        assert len(set(ids)) == len(ids)
        assert all(not c.get("outputs") for c in committed["cells"])  # committed without outputs


def test_cell_ids_follow_nbformat_rules():
    cell_id = _builder().cell_id
    assert cell_id("01_verify_the_theorems", 3) == "01_verify_the_theorems-03"
    assert cell_id("a b.c", 120) == "a-b-c-120"
    long = cell_id("x" * 100, 7)
    assert len(long) == 64 and long.endswith("-07")
    assert cell_id("", 0) == "cell-00"


@pytest.mark.parametrize("path", [_param(p) for p in NOTEBOOKS])
def test_notebook_runs_without_error(path, monkeypatch):
    if os.path.basename(path) in NEEDS_MITSUBA:
        pytest.importorskip("mitsuba")
    # the kernel inherits the environment: numba's cache outside the tree, as the Makefile does
    monkeypatch.setenv("NUMBA_CACHE_DIR", os.environ.get("NUMBA_CACHE_DIR",
                                                         os.path.join(ROOT, ".cache", "numba")))
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, kernel_name="python3", timeout=CELL_TIMEOUT,
                                     resources={"metadata": {"path": NB_DIR}})
    t0 = time.perf_counter()
    client.execute()    # raises CellExecutionError, naming the cell, on any error
    print(f"{os.path.basename(path)}: {time.perf_counter() - t0:.1f} s")
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
