"""Scenes and their cached high-spp references, shared by the benchmark scripts."""

from statmc.demo import cached_reference
from statmc.exr import read_exr
from statmc.renderers import make_renderer

#: Samples per pixel of the cached references in ``out/cache`` (65536 unless listed).
REF_SPP = {"glass-caustic": 32768}


def scene_reference(scene, renderer=None, cache="out/cache"):
    """``(renderer, reference PixelStats)`` of a built-in scene at its default size; the
    reference is rendered once (``statmc.demo.cached_reference``) and then read back."""
    r = renderer if renderer is not None else make_renderer(scene)
    _, path = cached_reference(r, REF_SPP.get(scene, 65536), cache)
    return r, read_exr(path)
