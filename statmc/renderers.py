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

__all__ = ["make_renderer", "list_scenes", "check_scene"]

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


def scene_expected() -> str:
    """What a scene argument must be, listing the built-in names: the end of the messages
    that refuse another (``make_renderer``'s, and the command line's SCENE)."""
    known = ", ".join(sorted(list_scenes()))
    return f"a built-in scene name ({known}) or the path of an existing Mitsuba XML file"


def check_scene(scene, name: str = "`scene`") -> str:
    """``scene`` as a string when it names a built-in scene (``toy:NAME`` or a Mitsuba one)
    or an existing path; else an :class:`InputError` naming it as ``name`` (the command line
    passes ``"SCENE"``), what was expected and what was given.  Whether an existing file is
    a scene Mitsuba can load is left to the loader."""
    if isinstance(scene, os.PathLike):
        scene = os.fspath(scene)
    if not isinstance(scene, str) or not scene:
        why = "an empty name" if scene == "" else f"of type {type(scene).__name__}"
        raise InputError(f"{name} must be {scene_expected()}; got {scene!r}, {why}.")
    if scene.startswith(TOY_PREFIX):
        from .toy import ToyRenderer
        if scene[len(TOY_PREFIX):] not in ToyRenderer.scenes():
            raise InputError(f"{name} must be {scene_expected()}; got {scene!r}, which is not "
                             "one of the toy scenes.")
        return scene
    from . import scenes
    if scene not in scenes.BUILTIN_SCENES and not os.path.exists(scene):
        raise InputError(f"{name} must be {scene_expected()}; got {scene!r}, which is neither "
                         "a built-in scene nor an existing file.")
    return scene


def make_renderer(scene, *, width: int | None = None, height: int | None = None, **options):
    """The renderer for ``scene`` (see module docstring), at ``width`` × ``height`` if given.

    ``scene`` is a built-in scene name (:func:`list_scenes`: ``toy:NAME`` or a Mitsuba
    scene) or the path (a ``str`` or ``os.PathLike``) of a Mitsuba XML file; anything else
    raises :class:`InputError` listing the built-in names.  ``options`` go to the
    renderer's constructor: for a Mitsuba scene, e.g. ``sensor=``
    and, for an XML file, ``params=`` (values of its ``$name`` parameters); see
    :class:`statmc.mitsuba_backend.MitsubaRenderer`."""
    scene = check_scene(scene)
    if scene.startswith(TOY_PREFIX):
        from .toy import ToyRenderer
        name = scene[len(TOY_PREFIX):]
        mitsuba_only = sorted(set(options) & {"sensor", "params", "variant", "chunk_samples"})
        if mitsuba_only:
            raise InputError(f"`{mitsuba_only[0]}` is an option of Mitsuba scenes; {scene!r} is "
                             "an analytic toy scene: leave it out.")
        kw = {k: v for k, v in (("width", width), ("height", height)) if v is not None}
        return ToyRenderer(name, **kw, **options)
    from .mitsuba_backend import MitsubaRenderer
    return MitsubaRenderer(scene, width=width, height=height, **options)
