"""Shared pytest set-up: property tests run with fixed examples.

Hypothesis draws derandomised examples so that CI on a fresh clone sees the same inputs
as a developer's run (statistical tests fix their own seeds).  ``HYPOTHESIS_PROFILE=explore``
turns the random search back on to hunt for new failures.
"""

import os

from hypothesis import settings

settings.register_profile("statmc", derandomize=True, deadline=None, print_blob=True)
settings.register_profile("explore", deadline=None, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "statmc"))
