"""Built-in Mitsuba 3 scenes, fully procedural (no external files).

Each scene is a Mitsuba scene dictionary with a ``box`` reconstruction filter (so a
sample belongs to the pixel it was drawn in, as :class:`statmc.mitsuba_backend.MitsubaRenderer`
assumes), an ``independent`` sampler and the ``path`` integrator.  Together they cover
the features whose noise the statistics in this package have to cope with:

============== ==================================================================
name           content
============== ==================================================================
cornell-box    Mitsuba's Cornell box: diffuse walls, one ceiling area light
glossy-spheres rough gold, rough plastic and anisotropic aluminium spheres
glass-caustic  a glass sphere lit by a tiny, very bright sphere light (caustics,
               fireflies)
textured-dof   procedural checkerboard floor, spheres at several depths, thin-lens
               camera (depth of field)
============== ==================================================================

:data:`BUILTIN_SCENES` maps names to one-line descriptions and never imports Mitsuba;
:func:`load_scene_dict` builds the dictionary with Mitsuba's current variant (setting one up
with :func:`statmc.mitsuba_backend.setup_mitsuba` if none is set, because transforms need one).
"""

from __future__ import annotations

import numbers

from .errors import InputError

__all__ = ["BUILTIN_SCENES", "DEFAULT_SIZES", "load_scene_dict"]

BUILTIN_SCENES: dict[str, str] = {
    "cornell-box": "Mitsuba's Cornell box: diffuse walls lit by one ceiling area light",
    "glossy-spheres": "rough gold, rough plastic and anisotropic aluminium spheres under an area light",
    "glass-caustic": "glass sphere lit by a tiny, very bright sphere light: caustics and fireflies",
    "textured-dof": "checkerboard floor and spheres at several depths seen by a thin-lens camera",
}

#: Default ``(width, height)`` of each scene: small, so tests stay quick.
DEFAULT_SIZES: dict[str, tuple[int, int]] = {
    "cornell-box": (128, 128),
    "glossy-spheres": (128, 96),
    "glass-caustic": (128, 96),
    "textured-dof": (128, 96),
}


def _check_size(name: str, value, default: int) -> int:
    if value is None:
        return default
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise InputError(f"`{name}` must be a positive integer number of pixels; got {value!r}.")
    return int(value)


def _film(width: int, height: int) -> dict:
    return {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
            "pixel_format": "rgb", "component_format": "float32", "sample_border": False}


def _sampler(spp: int = 16) -> dict:
    return {"type": "independent", "sample_count": spp}


def _rgb(v) -> dict:
    return {"type": "rgb", "value": list(v)}


def _floor(mi, material: dict, size: float = 8.0) -> dict:
    # rectangle lies in z = 0 facing +z; turn it to y = 0 facing +y
    return {"type": "rectangle", "bsdf": material,
            "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(size)}


def _cornell_box(mi, width: int, height: int) -> dict:
    d = mi.cornell_box()
    d["sensor"]["film"] = _film(width, height)
    d["sensor"]["sampler"] = _sampler()
    d["integrator"] = {"type": "path", "max_depth": 8}
    return d


def _glossy_spheres(mi, width: int, height: int) -> dict:
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 8},
        "sensor": {"type": "perspective", "fov": 32, "fov_axis": "x",
                   "to_world": T().look_at(origin=[0, 1.6, 6.0], target=[0, 0.45, 0], up=[0, 1, 0]),
                   "film": _film(width, height), "sampler": _sampler()},
        "floor": _floor(mi, {"type": "diffuse", "reflectance": _rgb([0.45, 0.45, 0.45])}),
        "back": {"type": "rectangle", "to_world": T().translate([0, 2, -2.5]).scale(6),
                 "bsdf": {"type": "diffuse", "reflectance": _rgb([0.3, 0.35, 0.45])}},
        "gold": {"type": "sphere", "center": [-1.25, 0.5, 0], "radius": 0.5,
                 "bsdf": {"type": "roughconductor", "material": "Au", "distribution": "ggx",
                          "alpha": 0.12}},
        "plastic": {"type": "sphere", "center": [0, 0.5, 0.3], "radius": 0.5,
                    "bsdf": {"type": "roughplastic", "distribution": "beckmann", "alpha": 0.08,
                             "diffuse_reflectance": _rgb([0.7, 0.08, 0.05])}},
        "aluminium": {"type": "sphere", "center": [1.25, 0.5, 0], "radius": 0.5,
                      "bsdf": {"type": "roughconductor", "material": "Al", "distribution": "ggx",
                               "alpha_u": 0.05, "alpha_v": 0.3}},
        "light": {"type": "rectangle",
                  "to_world": T().translate([0.8, 3.5, 1.5]).rotate([1, 0, 0], 90).scale(0.6),
                  "emitter": {"type": "area", "radiance": _rgb([20, 19, 17])}},
        "sky": {"type": "constant", "radiance": _rgb([0.12, 0.14, 0.18])},
    }


def _glass_caustic(mi, width: int, height: int) -> dict:
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 12},
        "sensor": {"type": "perspective", "fov": 38, "fov_axis": "x",
                   "to_world": T().look_at(origin=[0, 1.8, 4.5], target=[0, 0.4, 0], up=[0, 1, 0]),
                   "film": _film(width, height), "sampler": _sampler()},
        "floor": _floor(mi, {"type": "diffuse", "reflectance": _rgb([0.7, 0.7, 0.65])}),
        "back": {"type": "rectangle", "to_world": T().translate([0, 2, -2.0]).scale(6),
                 "bsdf": {"type": "diffuse", "reflectance": _rgb([0.55, 0.5, 0.45])}},
        "glass": {"type": "sphere", "center": [0, 0.6, 0], "radius": 0.6,
                  "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}},
        # a tiny, very bright light: caustic paths reach it only by BSDF sampling -> fireflies
        "bulb": {"type": "sphere", "center": [-0.9, 2.4, -0.6], "radius": 0.03,
                 "emitter": {"type": "area", "radiance": _rgb([4000, 3700, 3200])}},
        "sky": {"type": "constant", "radiance": _rgb([0.04, 0.045, 0.06])},
    }


def _textured_dof(mi, width: int, height: int) -> dict:
    T = mi.ScalarTransform4f
    checker = {"type": "checkerboard", "color0": _rgb([0.85, 0.82, 0.75]),
               "color1": _rgb([0.1, 0.1, 0.12]), "to_uv": T().scale([16, 16, 1])}
    colours = [[0.8, 0.15, 0.1], [0.15, 0.6, 0.2], [0.15, 0.3, 0.8], [0.8, 0.7, 0.1]]
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 6},
        # focused on the second sphere (distance ~ 4.0 from the camera)
        "sensor": {"type": "thinlens", "fov": 40, "fov_axis": "x", "aperture_radius": 0.2,
                   "focus_distance": 4.0,
                   "to_world": T().look_at(origin=[0, 1.2, 5.0], target=[0, 0.4, 0], up=[0, 1, 0]),
                   "film": _film(width, height), "sampler": _sampler()},
        "floor": _floor(mi, {"type": "diffuse", "reflectance": checker}),
        "light": {"type": "rectangle",
                  "to_world": T().translate([-1.5, 4.0, 2.0]).rotate([1, 0, 0], 90).scale(1.0),
                  "emitter": {"type": "area", "radiance": _rgb([9, 8.5, 8])}},
        "sky": {"type": "constant", "radiance": _rgb([0.25, 0.28, 0.33])},
    }
    for k, (x, z) in enumerate([(-1.6, 2.4), (-0.4, 1.0), (0.8, -0.6), (2.0, -2.4)]):
        bsdf = {"type": "diffuse", "reflectance": _rgb(colours[k])}
        if k % 2:
            bsdf = {"type": "roughplastic", "alpha": 0.15, "diffuse_reflectance": _rgb(colours[k])}
        d[f"sphere{k}"] = {"type": "sphere", "center": [x, 0.4, z], "radius": 0.4, "bsdf": bsdf}
    return d


_BUILDERS = {
    "cornell-box": _cornell_box,
    "glossy-spheres": _glossy_spheres,
    "glass-caustic": _glass_caustic,
    "textured-dof": _textured_dof,
}


def load_scene_dict(name: str, width: int | None = None, height: int | None = None) -> dict:
    """The Mitsuba scene dictionary of built-in scene ``name``.

    Parameters
    ----------
    name : str
        One of :data:`BUILTIN_SCENES`.
    width, height : int, optional
        Image size in pixels; defaults in :data:`DEFAULT_SIZES`.

    Returns
    -------
    dict
        Ready for ``mi.load_dict``: ``box`` filter, ``independent`` sampler, ``path``
        integrator.  Built with Mitsuba's current variant, which is set up by
        :func:`statmc.mitsuba_backend.setup_mitsuba` if none is set yet.

    Examples
    --------
    >>> d = load_scene_dict("cornell-box", 32, 24)
    >>> d["sensor"]["film"]["width"], d["sensor"]["film"]["rfilter"]["type"]
    (32, 'box')
    """
    if name not in _BUILDERS:
        raise InputError(f"`name` must be a built-in scene ({', '.join(sorted(_BUILDERS))}); "
                         f"got {name!r}.")
    dw, dh = DEFAULT_SIZES[name]
    w = _check_size("width", width, dw)
    h = _check_size("height", height, dh)
    from .mitsuba_backend import current_mitsuba
    return _BUILDERS[name](current_mitsuba(), w, h)
