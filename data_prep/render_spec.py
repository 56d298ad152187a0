"""The shared render setting of the denoiser (``conf/render/pairs.yaml``) as a typed object.

Both the training-pair generator (``dss-prep``) and the denoising pipeline at test time must
render with exactly the same camera model, light and splatting settings; they both build a
:class:`RenderSpec` from the same YAML block (:func:`load_render_spec` or the Hydra ``render``
group), and the block is copied verbatim into each dataset's manifest (``manifest["render"]``).

Two channels: ``point`` (diffuse shading under one point light fixed to the camera, the paper's
training renders) and ``planes`` (every pixel holds the camera-space plane of the surface it
shows, :func:`dss.shading.plane_coefficients`: depth and normal; ``conf/render/planes.yaml``).

Units: lengths are in bounding-box diagonals (clouds are normalised to a unit bbox diagonal
centred at the origin before rendering). Camera space: x right, y down, z forward.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["RenderSpec", "LightSpec", "View", "RenderSpecError", "load_render_spec", "default_spec_path",
           "SPEC_SHADINGS", "spec_path"]

#: the render channels a spec can have (the denoiser's input and output)
SPEC_SHADINGS = ("point", "planes")

_RENDERER_KEYS = ("K", "cutoff", "merge_threshold", "merge_fraction", "sigma", "sigma_k", "sigma_scale",
                  "filter_variance", "backface_culling", "znear", "background")


class RenderSpecError(ValueError):
    """An invalid render block (the message names the key)."""


def default_spec_path() -> Path:
    """``conf/render/pairs.yaml`` of the installed project."""
    return spec_path("pairs")


def spec_path(name: str) -> Path:
    """``conf/render/<name>.yaml`` of the installed project (``pairs``: the point light,
    ``planes``: the planes channel)."""
    import conf

    path = Path(conf.__file__).parent / "render" / f"{name}.yaml"
    if not path.is_file():
        raise FileNotFoundError(f"render spec {path} not found (have {sorted(q.stem for q in path.parent.glob('*.yaml'))})")
    return path


@dataclass(frozen=True)
class View:
    """One training view: look-at camera and camera-space light position (bbox-diagonal units)."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    light: tuple[float, float, float]

    def to_dict(self, focal: float) -> dict:
        return {"eye": list(self.eye), "target": list(self.target), "up": list(self.up), "focal": focal,
                "light_position_camera": list(self.light)}


@dataclass(frozen=True)
class LightSpec:
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    jitter: float = 0.0
    intensity: float = 1.0
    ambient: float = 0.1
    space: str = "camera"
    type: str = "point"


@dataclass(frozen=True)
class RenderSpec:
    """Camera sampling, light and renderer settings of the denoiser's renders.

    Attributes:
        image_size: (H, W) pixels.
        fov_deg: horizontal field of view; :attr:`focal` derives the focal length in pixels.
        distance: (min, max) camera distance to the target.
        target_jitter: std of the look-at target around the origin.
        up, up_jitter_deg: base up vector and the roll range about the viewing axis.
        light: the point light (camera space).
        renderer: keyword arguments of :class:`dss.render.RenderSettings`.
        backend: dss renderer backend (``auto``/``cpp``/``reference``); not part of the data.
    """

    image_size: tuple[int, int] = (128, 128)
    fov_deg: float = 40.0
    distance: tuple[float, float] = (0.9, 1.8)
    target_jitter: float = 0.05
    view_sampling: str = "uniform_sphere"
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    up_jitter_deg: float = 180.0
    shading: str = "point"
    light: LightSpec = field(default_factory=LightSpec)
    renderer: Mapping[str, Any] = field(default_factory=dict)
    backend: str = "auto"

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], where: str = "render config") -> RenderSpec:
        """Build and validate from a mapping (a DictConfig or dict, e.g. the YAML block)."""
        try:
            from omegaconf import DictConfig, OmegaConf

            if isinstance(cfg, DictConfig):
                cfg = OmegaConf.to_container(cfg, resolve=True)
        except ImportError:  # pragma: no cover
            pass
        cfg = dict(cfg)
        known = {"image_size", "fov_deg", "distance", "target_jitter", "view_sampling", "up", "up_jitter_deg",
                 "shading", "light", "renderer", "backend"}
        unknown = set(cfg) - known
        if unknown:
            raise RenderSpecError(f"{where}: unknown keys {sorted(unknown)}; known: {sorted(known)}")

        def err(key, msg):
            return RenderSpecError(f"{where}: {key}: {msg}")

        size = cfg.get("image_size", (128, 128))
        if isinstance(size, int):
            size = (size, size)
        if len(size) != 2 or any(int(s) <= 0 for s in size):
            raise err("image_size", f"must be [H, W] positive, got {size}")
        if any(int(s) % 4 for s in size):
            raise err("image_size", f"H and W must be multiples of 4 (pix2pix down/up-sampling), got {size}")
        fov = float(cfg.get("fov_deg", 40.0))
        if not 1.0 <= fov <= 170.0:
            raise err("fov_deg", f"must be in [1, 170], got {fov}")
        dist = tuple(float(d) for d in cfg.get("distance", (0.9, 1.8)))
        if len(dist) != 2 or not 0 < dist[0] <= dist[1]:
            raise err("distance", f"must be [min, max] with 0 < min <= max, got {dist}")
        tj = float(cfg.get("target_jitter", 0.05))
        if tj < 0:
            raise err("target_jitter", f"must be >= 0, got {tj}")
        vs = str(cfg.get("view_sampling", "uniform_sphere"))
        if vs != "uniform_sphere":
            raise err("view_sampling", f"only 'uniform_sphere' is implemented, got {vs!r}")
        up = tuple(float(u) for u in cfg.get("up", (0, 0, 1)))
        if len(up) != 3 or np.linalg.norm(up) == 0:
            raise err("up", f"must be a non-zero 3-vector, got {up}")
        upj = float(cfg.get("up_jitter_deg", 180.0))
        if not 0 <= upj <= 180:
            raise err("up_jitter_deg", f"must be in [0, 180], got {upj}")
        shading = str(cfg.get("shading", "point"))
        if shading not in SPEC_SHADINGS:
            raise err("shading", f"must be one of {list(SPEC_SHADINGS)} (the denoiser's render channel), got {shading!r}")
        lc = dict(cfg.get("light", {}) or {})
        bad = set(lc) - {"type", "space", "position", "jitter", "intensity", "ambient"}
        if bad:
            raise err("light", f"unknown keys {sorted(bad)}")
        if lc.get("type", "point") != "point" or lc.get("space", "camera") != "camera":
            raise err("light", "only a point light in camera space is supported")
        pos = tuple(float(p) for p in lc.get("position", (0, 0, 0)))
        if len(pos) != 3:
            raise err("light.position", f"must be a 3-vector, got {pos}")
        light = LightSpec(position=pos, jitter=float(lc.get("jitter", 0.0)),
                          intensity=float(lc.get("intensity", 1.0)), ambient=float(lc.get("ambient", 0.1)))
        if light.jitter < 0 or light.intensity < 0 or light.ambient < 0:
            raise err("light", "jitter, intensity and ambient must be >= 0")
        renderer = dict(cfg.get("renderer", {}) or {})
        bad = set(renderer) - set(_RENDERER_KEYS)
        if bad:
            raise err("renderer", f"unknown RenderSettings keys {sorted(bad)}; known: {list(_RENDERER_KEYS)}")
        backend = str(cfg.get("backend", "auto"))
        if backend not in ("auto", "cpp", "reference"):
            raise err("backend", f"must be auto, cpp or reference, got {backend!r}")
        spec = cls(image_size=(int(size[0]), int(size[1])), fov_deg=fov, distance=dist, target_jitter=tj,
                   view_sampling=vs, up=up, up_jitter_deg=upj, shading=shading, light=light,
                   renderer=renderer, backend=backend)
        try:
            spec.render_settings()
        except (TypeError, ValueError) as e:
            raise err("renderer", str(e)) from e
        return spec

    # ------------------------------------------------------------------ derived quantities
    @property
    def focal(self) -> float:
        """Focal length in pixels (from the horizontal field of view and the image width)."""
        return 0.5 * self.image_size[1] / math.tan(math.radians(self.fov_deg) / 2)

    def render_settings(self):
        """The :class:`dss.render.RenderSettings` of this spec."""
        from dss.render import RenderSettings

        kw = dict(self.renderer)
        if isinstance(kw.get("background"), list | tuple):
            kw["background"] = tuple(float(b) for b in kw["background"])
        return RenderSettings(**kw)

    def shader(self, light_position: Sequence[float] | None = None):
        """The ``shading`` argument of :func:`dss.render.render` for this spec's channel: its point
        light (at ``light_position``, camera space, when given) or ``"planes"``."""
        return "planes" if self.shading == "planes" else self.point_light(light_position)

    def describe_shading(self) -> str:
        """A short name of the channel for reports (``point light [x, y, z]`` or ``planes``)."""
        return "planes" if self.shading == "planes" else "point light " + str(list(self.light.position))

    def point_light(self, position: Sequence[float] | None = None):
        """A :class:`dss.shading.PointLight` at ``position`` (camera space; default: the spec's)."""
        from dss.shading import PointLight

        pos = tuple(float(p) for p in (self.light.position if position is None else position))
        return PointLight(position=pos, intensity=self.light.intensity, ambient=self.light.ambient)

    def cameras(self, views: Sequence[View]):
        """:class:`dss.cameras.Cameras` of ``views`` (V of them), at this spec's image size."""
        import torch

        from dss.cameras import look_at

        eye = torch.tensor([v.eye for v in views], dtype=torch.float32)
        target = torch.tensor([v.target for v in views], dtype=torch.float32)
        up = torch.tensor([v.up for v in views], dtype=torch.float32)
        return look_at(eye, target, up, self.focal, self.image_size)

    def sample_views(self, n: int, rng: np.random.Generator) -> list[View]:
        """``n`` random views: direction uniform on the sphere, distance uniform in the range,
        jittered target, up vector rolled about the viewing axis, light (optionally jittered)."""
        if n <= 0:
            raise ValueError(f"number of views must be positive, got {n}")
        views = []
        base_up = np.asarray(self.up, np.float64)
        base_up /= np.linalg.norm(base_up)
        for _ in range(n):
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            dist = rng.uniform(*self.distance)
            target = rng.normal(size=3) * self.target_jitter
            eye = target + dist * d
            f = -d  # viewing direction
            up = base_up
            if abs(f @ up) > 0.99:  # view along the up axis: take another reference
                up = np.array([1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
            up = up - (f @ up) * f
            up /= np.linalg.norm(up)
            ang = math.radians(rng.uniform(-self.up_jitter_deg, self.up_jitter_deg))
            up = up * math.cos(ang) + np.cross(f, up) * math.sin(ang)  # roll (up is orthogonal to f)
            light = np.asarray(self.light.position, np.float64)
            if self.light.jitter > 0:
                light = light + rng.normal(size=3) * self.light.jitter
            views.append(View(tuple(map(float, eye)), tuple(map(float, target)), tuple(map(float, up)),
                              tuple(map(float, light))))
        return views

    # ------------------------------------------------------------------ serialisation
    def to_dict(self, include_backend: bool = True) -> dict:
        """The manifest's ``render`` block (also what :meth:`from_config` reads back)."""
        d = {
            "image_size": list(self.image_size),
            "fov_deg": self.fov_deg,
            "focal": self.focal,
            "distance": list(self.distance),
            "target_jitter": self.target_jitter,
            "view_sampling": self.view_sampling,
            "up": list(self.up),
            "up_jitter_deg": self.up_jitter_deg,
            "shading": self.shading,
            "light": {**asdict(self.light), "position": list(self.light.position)},
            "renderer": dict(self.renderer),
        }
        if include_backend:
            d["backend"] = self.backend
        return d

    @classmethod
    def from_manifest(cls, render_block: Mapping[str, Any]) -> RenderSpec:
        """Rebuild the spec from a dataset manifest's ``render`` block."""
        d = dict(render_block)
        d.pop("focal", None)
        return cls.from_config(d, where="manifest render block")


def load_render_spec(path: str | Path | None = None, **overrides) -> RenderSpec:
    """Read the shared render spec (default ``conf/render/pairs.yaml``), with top-level overrides.

    >>> spec = load_render_spec(image_size=[256, 256])
    """
    from omegaconf import OmegaConf

    path = Path(path) if path is not None else default_spec_path()
    if not path.is_file():
        raise FileNotFoundError(f"render spec {path} not found")
    cfg = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    cfg.update(overrides)
    return RenderSpec.from_config(cfg, where=str(path))
