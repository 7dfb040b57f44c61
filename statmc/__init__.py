"""statmc: statistics of Monte Carlo rendering.

Per-pixel sample statistics with exact merging, EXR files in pbrt-v4's layout, error
metrics, renderers with per-pixel sample counts (an analytic toy renderer and Mitsuba 3),
and the statistical methods built on them.  ``import statmc`` never imports torch, and
loads Mitsuba and OIDN only when they are used.
"""

from .errors import FileFormatError, InputError
from .stats import PixelStats

__version__ = "0.1.0"

__all__ = ["PixelStats", "InputError", "FileFormatError", "__version__"]
