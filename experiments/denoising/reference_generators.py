"""Reference generators for ``dss-denoise`` / ``dss-filter``, and the render setup they imply.

A reference generator maps the renders of the input cloud to the images DSS should match:
``gen(images (V, H, W, C) tensor, mask=(V, H, W) bool) -> (V, H, W, C) tensor``. They are chosen
with the Hydra group ``conf/reference/{onnx,l0,slic,identity}.yaml`` (``_target_`` classes below):

- :class:`OnnxReference`: the Pix2Pix denoiser through onnxruntime (:mod:`pix2pix.runtime`),
  views in batches; the network output is masked with the render mask so the background stays
  background. The model file also fixes the render setup (:meth:`OnnxReference.render_spec`):
  image size and the render block of its training data.
- :class:`L0Reference`, :class:`SlicReference`, :class:`IdentityReference`: the image filters
  of :mod:`dss.filters` (L0 gradient smoothing, SLIC superpixels, no-op).
- :class:`OracleReference`: renders of the *clean* cloud through the same cameras, channel and
  renderer settings: the upper-bound control of a denoising comparison (needs ground truth).

Render setup (the one shared setting ``conf/render/pairs.yaml``, :mod:`data_prep.render_spec`):
:class:`SpecViewSampler` turns a :class:`RenderSpec` into the optimiser's per-cycle cameras
(farthest-point directions on the sphere, jittered, at the spec's distances, field of view,
target jitter and roll), since ``render_spec`` offers random training views only.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from data_prep.render_spec import RenderSpec, RenderSpecError, View, load_render_spec

log = logging.getLogger(__name__)

__all__ = [
    "ASSETS_DIR",
    "SHIPPED_MODELS",
    "ModelNotFoundError",
    "OnnxReference",
    "L0Reference",
    "SlicReference",
    "IdentityReference",
    "OracleReference",
    "AutoReference",
    "SpecViewSampler",
    "select_model",
    "spec_from_metadata",
]

#: where the shipped denoisers live (package data of ``experiments``)
ASSETS_DIR = Path(__file__).resolve().parents[1] / "assets"
#: noise level (fraction of the bbox diagonal) -> shipped model file name
SHIPPED_MODELS = {0.003: "denoiser_noise_0.3pct.onnx", 0.01: "denoiser_noise_1pct.onnx"}


class ModelNotFoundError(FileNotFoundError):
    """A requested denoiser file does not exist (the message says what to do)."""


def select_model(noise_level: float, assets_dir: str | Path | None = None) -> tuple[Path, float]:
    """The shipped model nearest to ``noise_level`` in log scale: (path, its noise level).

    Raises :class:`ModelNotFoundError` when that file is not there.
    """
    if not (noise_level > 0 and math.isfinite(noise_level)):
        raise ValueError(f"noise level must be a positive fraction of the bbox diagonal, got {noise_level}")
    level = min(SHIPPED_MODELS, key=lambda lv: abs(math.log(noise_level / lv)))
    path = Path(assets_dir) if assets_dir is not None else ASSETS_DIR
    path = path / SHIPPED_MODELS[level]
    if not path.is_file():
        raise ModelNotFoundError(
            f"denoiser model {path} (for noise {level:g}) does not exist. The shipped models are "
            "trained and exported with dss-train / dss-export; give one with reference.model=/path/"
            "to/model.onnx, or use an image filter instead: reference=l0"
        )
    return path, level


def spec_from_metadata(meta: dict[str, Any], fallback: RenderSpec | None = None) -> tuple[RenderSpec, str]:
    """The render spec of a denoiser's training data, from its ONNX metadata.

    ``dss.render_settings`` is the dataset manifest's ``render`` block; ``dss.render_image_size``
    the image size. A block that is not a full :class:`RenderSpec` (e.g. the synthetic test
    datasets of :mod:`pix2pix.testing`) falls back to ``fallback`` (default: the shared
    ``conf/render/pairs.yaml``) at the model's image size, with a warning.

    Returns:
        (spec, source): source is ``"model"`` or ``"fallback: <why>"``.
    """
    block = dict(meta.get("dss.render_settings") or {})
    size = meta.get("dss.render_image_size")
    try:
        if not block:
            raise RenderSpecError("the model has no render block")
        block.pop("backend", None)  # not part of the data; keep this machine's default
        if size:
            block["image_size"] = list(size)
        return RenderSpec.from_manifest(block), "model"
    except (RenderSpecError, TypeError, ValueError) as e:
        base = fallback or load_render_spec()
        spec = RenderSpec.from_manifest({**base.to_dict(), "image_size": list(size)}) if size else base
        why = str(e).splitlines()[0]
        log.warning("the model's render block is not a full render spec (%s); using %s at %s px",
                    why, "conf/render/pairs.yaml" if fallback is None else "the given spec", list(spec.image_size))
        return spec, f"fallback: {why}"


# --------------------------------------------------------------------------------- generators
class _Generator:
    """Common interface: ``__call__(images, mask=None)`` and a ``describe()`` dict."""

    name = "base"
    #: noise level the generator is made for (None: any)
    noise_level: float | None = None

    def render_spec(self, base: RenderSpec | None = None) -> tuple[RenderSpec, str]:
        """Render spec to use with this generator (filters: ``base`` or conf/render/pairs.yaml)."""
        return (base or load_render_spec()), "config"

    def describe(self) -> dict:
        return {"name": self.name}


class OnnxReference(_Generator):
    """The Pix2Pix denoiser as a reference generator.

    Args:
        model: path to a ``.onnx`` file written by ``dss-export``.
        threads: onnxruntime intra-op threads (None: all cores).
        max_batch: views per ``session.run``.
        noise: ignored here (the app uses it to pick ``model``); kept so one config serves both.
    """

    name = "onnx"

    def __init__(self, model: str | Path, threads: int | None = None, max_batch: int = 12, **_: Any):
        from pix2pix.runtime import OnnxDenoiser

        path = Path(model)
        if not path.is_file():
            raise ModelNotFoundError(f"denoiser model {path} does not exist")
        self.path = path
        self.denoiser = OnnxDenoiser(path, intra_op_num_threads=threads, max_batch=max_batch)
        self.noise_level = self.denoiser.noise_level
        # the renders it will get (3 channels at the model's render size, else the shared spec's)
        # fit the graph: refused at load otherwise, in one line
        self.denoiser.check_render(self.denoiser.render_image_size or load_render_spec().image_size, channels=3)

    def render_spec(self, base: RenderSpec | None = None) -> tuple[RenderSpec, str]:
        return spec_from_metadata(self.denoiser.metadata, base)

    @property
    def last_uncertainty(self) -> torch.Tensor | None:
        """(V, H, W) the predicted Laplace scale of each pixel's inverse depth in the latest call
        (a model trained with ``uncertainty``), else None; the plane fusion may read it."""
        ls = self.denoiser.last_log_scale
        return None if ls is None else torch.from_numpy(np.exp(ls[:, 0]))

    def __call__(self, images: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        x = images.detach().cpu().numpy()
        y = torch.from_numpy(self.denoiser.denoise_views(x, pad=True)).to(images)
        if mask is not None:
            # the network paints the background too; the reference keeps the render's background
            y = torch.where(mask[..., None].to(images.device), y, images)
        return y

    def describe(self) -> dict:
        m = self.denoiser.metadata
        return {"name": self.name, "model": str(self.path), "noise_level": self.noise_level,
                "model_name": m.get("dss.name"), "render_image_size": m.get("dss.render_image_size"),
                "epoch": m.get("dss.epoch")}


class _FilterReference(_Generator):
    filter_name = "identity"

    def __init__(self, **params: Any):
        from dss.filters import get_filter

        self.params = {k: v for k, v in params.items() if v is not None}
        self.fn = get_filter(self.filter_name, **self.params)
        self.name = self.filter_name

    def __call__(self, images: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        return self.fn(images, mask=mask)

    def describe(self) -> dict:
        return {"name": self.name, **self.params}


class L0Reference(_FilterReference):
    """L0 gradient smoothing (Xu et al. 2011); ``lam`` sets how flat the result is."""

    filter_name = "l0"

    def __init__(self, lam: float = 0.1, kappa: float = 2.0, beta_max: float = 1e5):
        super().__init__(lam=float(lam), kappa=float(kappa), beta_max=float(beta_max))


class SlicReference(_FilterReference):
    """SLIC superpixels, each filled with its mean colour."""

    filter_name = "slic"

    def __init__(self, n_segments: int = 150, compactness: float = 20.0, enforce_connectivity: bool = False):
        super().__init__(n_segments=int(n_segments), compactness=float(compactness),
                         enforce_connectivity=bool(enforce_connectivity))


class IdentityReference(_FilterReference):
    """The render itself: DSS then only applies its regularisers (a baseline)."""

    filter_name = "identity"

    def __init__(self):
        super().__init__()


class OracleReference(_Generator):
    """Renders of the clean cloud as references (the oracle control; DESIGN.md "Controls").

    The app binds the ground truth after normalising the input (:meth:`bind`): the clean points
    in the input's normalised frame, their normals, and the run's renderer settings, channel
    and backend. Each call renders them through the cameras of the input's renders; the
    references keep their own silhouette (``keep_background`` False).
    """

    name = "oracle"
    keep_background = False

    def __init__(self):
        self.points = self.normals = None
        self.settings, self.shading, self.backend = None, None, "auto"

    def bind(self, points: torch.Tensor, normals: torch.Tensor, settings, shading, backend: str = "auto") -> None:
        """Clean points and normals (M, 3) in the optimiser's frame, and how to render them."""
        self.points, self.normals = points.detach().float(), normals.detach().float()
        self.settings, self.shading, self.backend = settings, shading, backend

    def __call__(self, images: torch.Tensor, mask: torch.Tensor | None = None, cameras=None) -> torch.Tensor:
        from dss.render import render

        if self.points is None or cameras is None:
            raise RuntimeError("the oracle reference renders the clean cloud: bind() it first and pass the cameras")
        with torch.no_grad():
            out = render(self.points.to(images.device), self.normals.to(images.device), cameras, self.settings,
                         shading=self.shading, backend=self.backend)
        return out.images.to(images)

    def describe(self) -> dict:
        return {"name": self.name, "clean_points": None if self.points is None else int(len(self.points))}


def oracle_normals(clean: torch.Tensor, points: torch.Tensor, normals: torch.Tensor, k: int = 16,
                   mesh=None) -> torch.Tensor:
    """Normals (M, 3) of a clean cloud: its mesh's (the closest triangle's, when ``mesh`` is
    given in the clean cloud's frame), else a PCA fit over ``k`` neighbours; each signed like the
    nearest of ``points``' ``normals`` (the input's orientation, which the pipeline renders with)."""
    from dss.knn import knn
    from dss.pointcloud import estimate_normals

    if mesh is not None:
        from dss.metrics import mesh_normals_at

        n = torch.from_numpy(mesh_normals_at(clean.double().numpy(), mesh)).to(clean)
    else:
        n = estimate_normals(clean, k=k, orient="none").to(clean)
    j = knn(points, 1, query=clean).idx[:, 0].long()
    return torch.where((n * normals[j]).sum(1, keepdim=True) < 0, -n, n)


class AutoReference(_Generator):
    """``reference=auto``: the reference chosen per noise level from a table (``conf/reference/auto.yaml``).

    ``table``: ``{noise level: entry}``; the entry of the level nearest (in log scale) to the
    cloud's noise (the hint or the estimate) is used. An entry is a reference name (``identity``,
    ``oracle``, ``l0``, ``slic``: their ``conf/reference`` defaults; ``onnx``: the shipped model
    for the noise level), a model file (``*.onnx``; relative paths from the repository root,
    then from ``experiments/assets``), or a mapping ``{reference: <name or file>, fusion:
    {key: value}}`` whose ``fusion`` settings the job applies with it (a cascade model needs
    ``reference_cloud: refined``, a model with an uncertainty head may ask for ``uncertainty``).

    The job resolves it once the noise is known (:meth:`resolve_for_noise`); it is never called
    on images itself.
    """

    name = "auto"

    def __init__(self, table: dict | None = None, threads: int | None = None, max_batch: int = 12, **_: Any):
        if not table:
            raise ValueError("reference=auto needs reference.table ({noise level: reference name or model file})")
        self.table = {}
        for level, entry in dict(table).items():
            lv = float(level)
            if not (lv > 0 and math.isfinite(lv)):
                raise ValueError(f"reference.table: noise level {level!r} is not a positive fraction of the diagonal")
            self.table[lv] = _auto_entry(entry)
        self.threads, self.max_batch = threads, int(max_batch)

    def entry_for(self, noise: float) -> tuple[float, dict]:
        """(table level, entry {"reference": ..., "fusion": {...}}) for ``noise``."""
        if not (noise and noise > 0 and math.isfinite(noise)):
            raise ValueError(f"reference=auto needs a positive noise level, got {noise}")
        level = min(self.table, key=lambda lv: abs(math.log(noise / lv)))
        return level, self.table[level]

    def resolve_for_noise(self, noise: float) -> tuple[_Generator, str, dict]:
        """(the generator, a note for metrics.json, the fusion settings that come with it)."""
        level, entry = self.entry_for(noise)
        ref = entry["reference"]
        if ref in _NAMED:
            gen = _NAMED[ref]()
            what = ref
        else:
            if ref == "onnx":
                path, _ = select_model(noise)
            else:
                path = _model_path(ref)
            gen = OnnxReference(path, threads=self.threads, max_batch=self.max_batch)
            what = str(path)
        fusion = dict(entry.get("fusion") or {})
        note = (f"reference=auto: {what} (table level {level:g} for noise {noise:.4g})"
                + (f", fusion {fusion}" if fusion else ""))
        return gen, note, fusion

    def __call__(self, images, mask=None):
        raise RuntimeError("reference=auto must be resolved for the noise level first (resolve_for_noise)")

    def describe(self) -> dict:
        return {"name": self.name, "table": {str(k): v for k, v in self.table.items()}}


#: the reference names an auto table may use besides model files and "onnx"
_NAMED = {"identity": lambda: IdentityReference(), "oracle": lambda: OracleReference(),
          "l0": lambda: L0Reference(), "slic": lambda: SlicReference()}


def _auto_entry(entry) -> dict:
    if isinstance(entry, str):
        entry = {"reference": entry}
    try:
        entry = dict(entry)
    except (TypeError, ValueError):
        raise ValueError(f"reference.table: entry {entry!r} is not a reference name, a model file or a mapping") from None
    bad = set(entry) - {"reference", "fusion"}
    ref = entry.get("reference")
    if bad or not isinstance(ref, str) or not ref:
        raise ValueError(f"reference.table: entry {entry!r} must be a name, a .onnx file or "
                         "{reference: ..., fusion: {...}}")
    if ref not in _NAMED and ref != "onnx" and not ref.endswith(".onnx"):
        raise ValueError(f"reference.table: {ref!r} is neither a reference name ({sorted(_NAMED)} or onnx) "
                         "nor a .onnx model file")
    return {"reference": ref, "fusion": dict(entry.get("fusion") or {})}


def _model_path(ref: str) -> Path:
    p = Path(ref).expanduser()
    for cand in ([p] if p.is_absolute() else [ASSETS_DIR.parent.parent / p, ASSETS_DIR / p]):
        if cand.is_file():
            return cand
    raise ModelNotFoundError(f"reference.table names the model {ref}, which does not exist (relative paths are "
                             f"looked up from the repository root and from {ASSETS_DIR})")


# --------------------------------------------------------------------------------- cameras
class SpecViewSampler:
    """Per-cycle cameras with a render spec's camera model, covering the sphere.

    Directions: farthest-point sampling of a Fibonacci lattice from a random start, each
    perturbed by Gaussian noise of std ``jitter`` (the paper's view sampling). Per view, as in
    the spec's training views: distance uniform in ``spec.distance`` (times ``distance_scale``),
    look-at target ``center`` plus Gaussian jitter of std ``spec.target_jitter``, up vector
    ``spec.up`` rolled by U(-up_jitter_deg, up_jitter_deg). Lengths are in bbox diagonals: the
    cloud is expected normalised (``center`` = its bbox centre, default the origin).

    ``sample() -> Cameras`` (V views at ``spec.image_size``), as the optimiser expects.
    """

    def __init__(self, spec: RenderSpec, views: int = 12, seed: int = 0, jitter: float = 0.1,
                 center=(0.0, 0.0, 0.0), distance_scale: float = 1.0):
        if views <= 0:
            raise ValueError(f"views must be positive, got {views}")
        self.spec = spec
        self.views = int(views)
        self.jitter = float(jitter)
        self.center = np.asarray(center, np.float64)
        self.distance_scale = float(distance_scale)
        self.rng = np.random.default_rng(seed)
        from dss.cameras import fibonacci_sphere

        self._lattice = fibonacci_sphere(1000).double().numpy()

    def directions(self) -> np.ndarray:
        from dss.cameras import farthest_point_sampling

        start = int(self.rng.integers(len(self._lattice)))
        idx = farthest_point_sampling(torch.from_numpy(self._lattice), self.views, start).numpy()
        d = self._lattice[idx] + self.jitter * self.rng.normal(size=(self.views, 3))
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def sample_views(self) -> list[View]:
        s = self.spec
        base_up = np.asarray(s.up, np.float64)
        base_up /= np.linalg.norm(base_up)
        views = []
        for d in self.directions():
            dist = self.rng.uniform(*s.distance) * self.distance_scale
            target = self.center + self.rng.normal(size=3) * s.target_jitter
            eye = target + dist * d
            f = -d
            up = base_up
            if abs(f @ up) > 0.99:
                up = np.array([1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
            up = up - (f @ up) * f
            up /= np.linalg.norm(up)
            ang = math.radians(self.rng.uniform(-s.up_jitter_deg, s.up_jitter_deg))
            up = up * math.cos(ang) + np.cross(f, up) * math.sin(ang)
            views.append(View(tuple(map(float, eye)), tuple(map(float, target)), tuple(map(float, up)),
                              tuple(map(float, s.light.position))))
        return views

    def sample(self):
        return self.spec.cameras(self.sample_views())
