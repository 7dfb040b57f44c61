"""One entry point for every renderer: the analytic toy renderer and Mitsuba 3.

A renderer has ``height``, ``width``, ``channels``, ``name`` and
``render(counts, *, seed=0, progress=False) -> PixelStats`` that draws exactly
``counts[i, j]`` samples in pixel ``(i, j)``.  Scene names:

* ``toy:NAME`` — :class:`statmc.toy.ToyRenderer` (exact per-pixel mean and variance);
* a built-in Mitsuba scene name (:data:`statmc.scenes.BUILTIN_SCENES`) or a path to a
  Mitsuba XML file — :class:`statmc.mitsuba_backend.MitsubaRenderer`.
"""

from __future__ import annotations

import os

from .errors import InputError

__all__ = ["make_renderer", "list_scenes"]

TOY_PREFIX = "toy:"


def list_scenes() -> dict[str, str]:
    """Built-in scene names (toy and Mitsuba) with one-line descriptions."""
    from . import scenes
    from .toy import ToyRenderer
    toys = ToyRenderer.scenes()
    if not isinstance(toys, dict):
        toys = {k: "analytic toy scene" for k in toys}
    out = {f"{TOY_PREFIX}{k}": v for k, v in toys.items()}
    out.update(scenes.BUILTIN_SCENES)
    return out


def make_renderer(scene: str, *, width: int | None = None, height: int | None = None, **options):
    """The renderer for ``scene`` (see module docstring), at ``width`` × ``height`` if given.

    ``options`` go to the renderer's constructor: for a Mitsuba scene, e.g. ``sensor=``
    and, for an XML file, ``params=`` (values of its ``$name`` parameters); see
    :class:`statmc.mitsuba_backend.MitsubaRenderer`."""
    if not isinstance(scene, str) or not scene:
        raise InputError(f"`scene` must be a scene name or a Mitsuba XML path; got {scene!r}.")
    if scene.startswith(TOY_PREFIX):
        from .toy import ToyRenderer
        name = scene[len(TOY_PREFIX):]
        if name not in ToyRenderer.scenes():
            known = ", ".join(TOY_PREFIX + k for k in ToyRenderer.scenes())
            raise InputError(f"unknown toy scene {scene!r}; expected one of {known}.")
        mitsuba_only = sorted(set(options) & {"sensor", "params", "variant", "chunk_samples"})
        if mitsuba_only:
            raise InputError(f"`{mitsuba_only[0]}` is an option of Mitsuba scenes; {scene!r} is "
                             "an analytic toy scene: leave it out.")
        kw = {k: v for k, v in (("width", width), ("height", height)) if v is not None}
        return ToyRenderer(name, **kw, **options)
    from . import scenes
    if scene not in scenes.BUILTIN_SCENES and not os.path.exists(scene):
        known = ", ".join(sorted(list_scenes()))
        raise InputError(f"scene {scene!r} is neither a file nor a built-in scene ({known}).")
    from .mitsuba_backend import MitsubaRenderer
    return MitsubaRenderer(scene, width=width, height=height, **options)
