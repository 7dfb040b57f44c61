"""Every ``>>>`` example in the docstrings of ``statmc`` and ``statmc.nn`` runs and is checked.

One test per module with examples.  The modules whose doctests an older test file already
runs (:data:`ELSEWHERE`) are not run again here; instead a cheap check makes sure that
every module with examples is run by exactly one of the two, that no example is switched
off with ``+SKIP``, and that doctest *finds* every ``>>>`` line written in the source (an
example in a comment or in the docstring of an object doctest does not collect would
otherwise never run).

Only ``NORMALIZE_WHITESPACE`` is on.  ``ELLIPSIS`` is deliberately off: an example that
needs ``...`` for a genuinely machine-dependent value (a timing, an address) must say so
itself with ``# doctest: +ELLIPSIS``, so that no value gets hidden by accident.
"""

from __future__ import annotations

import doctest
import importlib
import os
import re
import tempfile
from pathlib import Path

import pytest

os.environ.setdefault("NUMBA_CACHE_DIR",
                      str(Path(__file__).resolve().parents[1] / ".cache" / "numba"))

ROOT = Path(__file__).resolve().parents[1]
FLAGS = doctest.NORMALIZE_WHITESPACE

#: Modules whose doctests run in another test file (module -> that file).
ELSEWHERE = {
    "statmc.analytic": "test_analytic.py",
    "statmc.denoisers": "test_denoisers.py",
    "statmc.sure": "test_sure.py",
    "statmc.toy": "test_toy.py",
}

#: Modules whose doctests run here; the Mitsuba ones render or build scenes.
HERE = [
    "statmc.combine",
    "statmc.da_sampling",
    "statmc.exr",
    "statmc.filters",
    "statmc.gem",
    "statmc.metrics",
    pytest.param("statmc.mitsuba_backend", marks=pytest.mark.mitsuba),
    "statmc.progressive",
    pytest.param("statmc.scenes", marks=pytest.mark.mitsuba),
    "statmc.stats",
    "statmc.nn.ops",
]
_HERE_NAMES = [p if isinstance(p, str) else p.values[0] for p in HERE]

_PROMPT = re.compile(r"^\s*>>> ", re.MULTILINE)


def _source_files():
    """module name -> source file, for every module of statmc and statmc.nn."""
    out = {}
    for pkg, folder in (("statmc", ROOT / "statmc"), ("statmc.nn", ROOT / "nn")):
        for f in sorted(folder.glob("*.py")):
            name = pkg if f.stem == "__init__" else f"{pkg}.{f.stem}"
            out[name] = f
    return out


def _n_prompts(name):
    return len(_PROMPT.findall(_source_files()[name].read_text(encoding="utf-8")))


def _import(name):
    if name.startswith("statmc.nn"):
        pytest.importorskip("torch")
    return importlib.import_module(name)


def test_every_module_with_examples_is_run_exactly_once():
    with_examples = {name for name, f in _source_files().items()
                     if _PROMPT.search(f.read_text(encoding="utf-8"))}
    here, elsewhere = set(_HERE_NAMES), set(ELSEWHERE)
    assert not here & elsewhere, f"run twice: {sorted(here & elsewhere)}"
    assert with_examples == here | elsewhere, (
        f"modules with examples but no doctest run: {sorted(with_examples - here - elsewhere)}; "
        f"listed but without examples: {sorted((here | elsewhere) - with_examples)}")
    for name, test_file in ELSEWHERE.items():
        text = (ROOT / "tests" / test_file).read_text(encoding="utf-8")
        assert "doctest.testmod(" in text, f"{test_file} no longer runs the doctests of {name}"


def test_no_example_is_skipped():
    skipped = [f"{f.relative_to(ROOT)}:{i}" for f in _source_files().values()
               for i, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1)
               if ">>> " in line and "+SKIP" in line]
    assert not skipped, f"examples switched off with +SKIP: {skipped}"


@pytest.mark.parametrize("name", sorted(ELSEWHERE))
def test_examples_run_elsewhere_are_all_found(name):
    """The other files assert ``failed == 0`` but only a lower bound on ``attempted``."""
    mod = _import(name)
    found = sum(len(t.examples) for t in doctest.DocTestFinder().find(mod))
    assert found == _n_prompts(name)


@pytest.mark.parametrize("name", HERE)
def test_docstring_examples(name, tmp_path, monkeypatch):
    mod = _import(name)
    # the examples' temporary files go to a folder of their own, which they must leave empty
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    result = doctest.testmod(mod, optionflags=FLAGS)
    assert not list(scratch.iterdir()), f"examples left behind: {sorted(p.name for p in scratch.iterdir())}"
    assert result.failed == 0, "see the captured stdout for the failing examples"
    # every `>>>` line of the source is one example; a skipped or uncollected one is not attempted
    n = _n_prompts(name)
    assert result.attempted == n, f"doctest ran {result.attempted} of the {n} examples in the source"
