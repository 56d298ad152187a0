"""Classical point cloud denoising baselines, run by their maintained implementations.

Each method is a function ``f(points (N,3) float64, normals (N,3)|None, **params) -> (N',3)``
(or ``(points, normals)``), called inside the worker subprocess of
:mod:`experiments.evaluation.baselines.runner` so that a crash or hang of a third-party library never
takes the caller down. Heavy packages are imported inside the functions.

Scale-dependent parameters are given in units of the cloud's mean nearest-neighbour spacing
(``*_spacing`` factors); the worker records the absolute values it used under ``resolved``.

Registered methods (``METHODS``):

* ``cgal_jet`` -- CGAL ``jet_smooth_point_set`` (Cazals & Pouget 2005 jet fitting).
* ``cgal_bilateral`` -- CGAL ``bilateral_smooth_point_set`` (Huang et al. 2013, EAR's
  edge-aware bilateral projection), iterated.
* ``cgal_wlop`` -- CGAL ``wlop_simplify_and_regularize_point_set`` (Huang et al. 2009), keeping
  100% of the points.
* ``open3d_mls``, ``open3d_bilateral``, ``open3d_taubin``, ``open3d_laplacian`` -- the point
  cloud smoothing methods of ``open3d.geometry.PointCloud`` (``smooth_mls``,
  ``smooth_bilateral``, ``smooth_taubin``, ``smooth_laplacian``). Upstream Open3D releases up
  to 0.19 have no point cloud smoothing; these exist in the Open3D build installed here and
  are reported 'unavailable' where the method is missing.
* ``meshlab_rimls``, ``meshlab_apss`` -- pymeshlab ``compute_mls_projection_rimls`` /
  ``compute_mls_projection_apss`` (Oeztireli et al. 2009 RIMLS; Guennebaud & Gross 2007
  APSS), projecting the points onto the MLS surface of themselves. These filters crash
  (SIGSEGV) in some pymeshlab builds (2023.12.post3 and 2025.7.post1 on our Linux x86-64 test
  machine, on MeshLab's own sample meshes too); the runner records that as a crash.
* ``meshlab_rimls_mc``, ``meshlab_apss_mc`` -- the same MLS surfaces extracted with MeshLab's
  marching cubes (``generate_marching_cubes_rimls`` / ``_apss``, which work there), then each
  point moved to its closest point on that surface (open3d RaycastingScene).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np


class MethodUnavailable(RuntimeError):
    """The method's package (or the needed function in it) is not installed."""


@dataclass(frozen=True)
class Method:
    name: str
    func: Callable[..., Any]
    requires: tuple[str, ...]  # importable module names
    defaults: dict = field(default_factory=dict)
    description: str = ""
    needs_normals: bool = False


# --------------------------------------------------------------------------------------------
# helpers (run in the worker)
# --------------------------------------------------------------------------------------------
def mean_spacing(points: np.ndarray, k: int = 1) -> float:
    """Mean distance from each point to its k-th nearest other point."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points, k=k + 1, workers=-1)
    return float(np.mean(d[:, k]))


def _pca_normals(points: np.ndarray, k: int = 16, orient: bool = True) -> np.ndarray:
    """PCA normals from k neighbours; ``orient``: made consistent by Open3D's tangent-plane
    MST propagation, then flipped so most point away from the centroid (implicit MLS
    surfaces need consistently oriented normals)."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(int(k)))
    if orient:
        pc.orient_normals_consistent_tangent_plane(int(k))
    n = np.asarray(pc.normals)
    if orient and np.sum((points - points.mean(axis=0)) * n) < 0:
        n = -n
    return n


def _workdir() -> str:
    # the worker sets this to its private temporary directory
    return os.environ.get("DSS_BASELINE_WORKDIR") or os.getcwd()


def _to_cgal(points: np.ndarray, normals: np.ndarray | None):
    from CGAL.CGAL_Point_set_3 import Point_set_3

    path = os.path.join(_workdir(), "cgal_in.xyz")
    data = points if normals is None else np.hstack([points, normals])
    np.savetxt(path, data, fmt="%.10g")
    ps = Point_set_3()
    ps.read(path)
    if ps.size() != len(points):
        raise RuntimeError(f"CGAL read {ps.size()} of {len(points)} points")
    return ps


def _from_cgal(ps) -> np.ndarray:
    path = os.path.join(_workdir(), "cgal_out.xyz")
    ps.write(path)
    out = np.loadtxt(path, ndmin=2)
    return out[:, :3]


def _resolved(**kv) -> dict:
    return {"resolved": kv}


# --------------------------------------------------------------------------------------------
# CGAL
# --------------------------------------------------------------------------------------------
def cgal_jet(points, normals=None, k=24, degree_fitting=2, degree_monge=2, iterations=1):
    """CGAL jet smoothing: each point moves onto the jet (local polynomial) fitted to its k
    nearest neighbours."""
    from CGAL import CGAL_Point_set_processing_3 as psp

    ps = _to_cgal(points, None)
    for _ in range(int(iterations)):
        psp.jet_smooth_point_set(ps, int(k), 0.0, int(degree_fitting), int(degree_monge))
    return _from_cgal(ps)


def cgal_bilateral(points, normals=None, k=32, sharpness_angle=25.0, iterations=3, normal_k=16):
    """CGAL bilateral (edge-aware) smoothing; needs normals (PCA-estimated when absent)."""
    from CGAL import CGAL_Point_set_processing_3 as psp

    if normals is None:
        normals = _pca_normals(points, int(normal_k))
    ps = _to_cgal(points, normals)
    for _ in range(int(iterations)):
        psp.bilateral_smooth_point_set(ps, int(k), 0.0, float(sharpness_angle))
    return _from_cgal(ps)


def cgal_wlop(
    points,
    normals=None,
    select_percentage=100.0,
    radius_spacing=4.0,
    iterations=35,
    require_uniform_sampling=False,
):
    """CGAL WLOP (weighted locally optimal projection), keeping ``select_percentage`` % of the
    points. ``radius_spacing`` < 0 lets CGAL estimate the neighbourhood radius."""
    from CGAL import CGAL_Point_set_processing_3 as psp
    from CGAL.CGAL_Point_set_3 import Point_set_3

    radius = -1.0 if radius_spacing < 0 else float(radius_spacing) * mean_spacing(points)
    ps = _to_cgal(points, None)
    out = Point_set_3()
    psp.wlop_simplify_and_regularize_point_set(
        ps, out, float(select_percentage), radius, int(iterations), bool(require_uniform_sampling)
    )
    return (
        _from_cgal(out),
        None,
        _resolved(neighbor_radius=radius if radius > 0 else "CGAL estimate"),
    )


# --------------------------------------------------------------------------------------------
# Open3D
# --------------------------------------------------------------------------------------------
def _o3d_cloud(points, normals):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(normals)
    return pc


def _o3d_method(name: str):
    import open3d as o3d

    fn = getattr(o3d.geometry.PointCloud, name, None)
    if fn is None:
        raise MethodUnavailable(
            f"open3d {o3d.__version__} has no PointCloud.{name} (point cloud smoothing is not "
            "part of upstream Open3D releases)"
        )
    return fn


def open3d_mls(points, normals=None, radius_spacing=5.0, max_nn=30):
    """Open3D ``PointCloud.smooth_mls``: projection onto a Gaussian-weighted local PCA plane."""
    import open3d as o3d

    fn = _o3d_method("smooth_mls")
    r = float(radius_spacing) * mean_spacing(points)
    out = fn(_o3d_cloud(points, normals), o3d.geometry.KDTreeSearchParamHybrid(r, int(max_nn)))
    return np.asarray(out.points), None, _resolved(radius=r)


def open3d_bilateral(
    points, normals=None, radius_spacing=5.0, max_nn=60, sigma_s_spacing=2.0, sigma_r_spacing=3.0
):
    """Open3D ``PointCloud.smooth_bilateral``: spatial x normal-direction weighted average."""
    import open3d as o3d

    fn = _o3d_method("smooth_bilateral")
    h = mean_spacing(points)
    r, ss, sr = float(radius_spacing) * h, float(sigma_s_spacing) * h, float(sigma_r_spacing) * h
    out = fn(
        _o3d_cloud(points, normals), o3d.geometry.KDTreeSearchParamHybrid(r, int(max_nn)), ss, sr
    )
    return np.asarray(out.points), None, _resolved(radius=r, sigma_s=ss, sigma_r=sr)


def open3d_taubin(points, normals=None, iterations=10, lambda_=0.5, mu=-0.53, knn=20):
    """Open3D ``PointCloud.smooth_taubin`` on the k-NN graph (uniform weights)."""
    fn = _o3d_method("smooth_taubin")
    out = fn(_o3d_cloud(points, normals), int(iterations), float(lambda_), float(mu), int(knn))
    return np.asarray(out.points)


def open3d_laplacian(points, normals=None, iterations=3, lambda_=0.5, knn=20):
    """Open3D ``PointCloud.smooth_laplacian`` on the k-NN graph (shrinks the shape)."""
    fn = _o3d_method("smooth_laplacian")
    out = fn(_o3d_cloud(points, normals), int(iterations), float(lambda_), int(knn))
    return np.asarray(out.points)


# --------------------------------------------------------------------------------------------
# MeshLab
# --------------------------------------------------------------------------------------------
def _meshlab_projection(filter_name, points, normals, normal_k, **kw):
    import pymeshlab

    if normals is None:
        normals = _pca_normals(points, int(normal_k))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=points, v_normals_matrix=normals))
    ms.generate_copy_of_current_mesh()  # mesh 1 is projected onto the MLS surface of mesh 0
    getattr(ms, filter_name)(controlmesh=0, proxymesh=1, **kw)
    return np.asarray(ms.mesh(ms.mesh_number() - 1).vertex_matrix())


def meshlab_rimls(
    points,
    normals=None,
    filterscale=2.0,
    sigman=0.75,
    maxprojectioniters=15,
    maxrefittingiters=3,
    normal_k=16,
):
    """MeshLab RIMLS projection (robust implicit MLS) of the points onto their own surface."""
    return _meshlab_projection(
        "compute_mls_projection_rimls",
        points,
        normals,
        normal_k,
        filterscale=float(filterscale),
        sigman=float(sigman),
        maxprojectioniters=int(maxprojectioniters),
        maxrefittingiters=int(maxrefittingiters),
    )


def meshlab_apss(
    points,
    normals=None,
    filterscale=2.0,
    sphericalparameter=1.0,
    maxprojectioniters=15,
    normal_k=16,
):
    """MeshLab APSS projection (algebraic point set surfaces) of the points."""
    return _meshlab_projection(
        "compute_mls_projection_apss",
        points,
        normals,
        normal_k,
        filterscale=float(filterscale),
        sphericalparameter=float(sphericalparameter),
        maxprojectioniters=int(maxprojectioniters),
    )


def _meshlab_mc_project(filter_name, points, normals, normal_k, **kw):
    import open3d as o3d
    import pymeshlab

    if normals is None:
        normals = _pca_normals(points, int(normal_k))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=points, v_normals_matrix=normals))
    getattr(ms, filter_name)(**kw)  # adds the marching-cubes mesh of the MLS surface
    mesh = ms.current_mesh()
    v, f = mesh.vertex_matrix(), mesh.face_matrix()
    if len(f) == 0:
        raise RuntimeError(f"{filter_name} produced an empty surface")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    ans = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    return (
        np.asarray(ans["points"].numpy(), dtype=np.float64),
        None,
        _resolved(surface_vertices=int(len(v)), surface_faces=int(len(f))),
    )


def meshlab_rimls_mc(
    points,
    normals=None,
    filterscale=2.0,
    sigman=0.75,
    maxprojectioniters=15,
    maxrefittingiters=3,
    resolution=200,
    normal_k=16,
):
    """MeshLab RIMLS surface (marching cubes at ``resolution``), each point then moved to its
    closest surface point: RIMLS by the route that does not crash here."""
    return _meshlab_mc_project(
        "generate_marching_cubes_rimls",
        points,
        normals,
        normal_k,
        filterscale=float(filterscale),
        sigman=float(sigman),
        maxprojectioniters=int(maxprojectioniters),
        maxrefittingiters=int(maxrefittingiters),
        resolution=int(resolution),
    )


def meshlab_apss_mc(
    points,
    normals=None,
    filterscale=2.0,
    sphericalparameter=1.0,
    maxprojectioniters=15,
    resolution=200,
    normal_k=16,
):
    """MeshLab APSS surface (marching cubes), each point moved to its closest surface point."""
    return _meshlab_mc_project(
        "generate_marching_cubes_apss",
        points,
        normals,
        normal_k,
        filterscale=float(filterscale),
        sphericalparameter=float(sphericalparameter),
        maxprojectioniters=int(maxprojectioniters),
        resolution=int(resolution),
    )


def _defaults(fn) -> dict:
    import inspect

    return {
        k: p.default
        for k, p in inspect.signature(fn).parameters.items()
        if k not in ("points", "normals") and p.default is not inspect.Parameter.empty
    }


def _m(name, fn, requires, needs_normals=False) -> Method:
    doc = " ".join((fn.__doc__ or "").strip().split("\n\n")[0].split())
    return Method(name, fn, requires, _defaults(fn), doc, needs_normals)


METHODS: dict[str, Method] = {
    m.name: m
    for m in [
        _m("cgal_jet", cgal_jet, ("CGAL",)),
        _m("cgal_bilateral", cgal_bilateral, ("CGAL", "open3d")),
        _m("cgal_wlop", cgal_wlop, ("CGAL",)),
        _m("open3d_mls", open3d_mls, ("open3d",)),
        _m("open3d_bilateral", open3d_bilateral, ("open3d",)),
        _m("open3d_taubin", open3d_taubin, ("open3d",)),
        _m("open3d_laplacian", open3d_laplacian, ("open3d",)),
        _m("meshlab_rimls", meshlab_rimls, ("pymeshlab", "open3d")),
        _m("meshlab_apss", meshlab_apss, ("pymeshlab", "open3d")),
        _m("meshlab_rimls_mc", meshlab_rimls_mc, ("pymeshlab", "open3d")),
        _m("meshlab_apss_mc", meshlab_apss_mc, ("pymeshlab", "open3d")),
    ]
}

#: pip package that provides each importable module (for 'unavailable' messages).
PIP_NAMES = {"CGAL": "cgal", "pymeshlab": "pymeshlab", "open3d": "open3d"}


#: Parameter presets per noise level (fraction of the bounding-box diagonal). The defaults
#: above are the ``0.003`` preset. Chosen by a small grid search (2-6 values per parameter,
#: Chamfer ``paper`` protocol) on Kangaroo_V10k, 20K Poisson-disk points, one seed: tuned,
#: not exhaustively; a sweep may do better. Scale-free (``*_spacing``) so they transfer
#: across densities only approximately.
PRESETS: dict[str, dict[float, dict]] = {
    "cgal_jet": {0.003: {"k": 24, "iterations": 1}, 0.01: {"k": 96, "iterations": 1}},
    "cgal_bilateral": {0.003: {"k": 32, "iterations": 3}, 0.01: {"k": 64, "iterations": 6}},
    "cgal_wlop": {
        0.003: {"radius_spacing": 4.0, "iterations": 35},
        0.01: {"radius_spacing": 8.0, "iterations": 10},
    },
    "open3d_mls": {
        0.003: {"radius_spacing": 5.0, "max_nn": 30},
        0.01: {"radius_spacing": 8.0, "max_nn": 100},
    },
    "open3d_bilateral": {
        0.003: {"radius_spacing": 5.0, "sigma_s_spacing": 2.0, "sigma_r_spacing": 3.0},
        0.01: {"radius_spacing": 5.0, "sigma_s_spacing": 4.0, "sigma_r_spacing": 3.0},
    },
    "open3d_taubin": {0.003: {"iterations": 10, "knn": 20}, 0.01: {"iterations": 10, "knn": 20}},
    "open3d_laplacian": {0.003: {"iterations": 3}, 0.01: {"iterations": 5}},
    "meshlab_rimls": {0.003: {"filterscale": 4.0}, 0.01: {"filterscale": 4.0, "normal_k": 48}},
    "meshlab_apss": {0.003: {"filterscale": 4.0}, 0.01: {"filterscale": 4.0, "normal_k": 48}},
    # at 1% noise the marching-cubes route barely beats the input (Chamfer 1.06 vs 1.14)
    "meshlab_rimls_mc": {0.003: {"filterscale": 4.0}, 0.01: {"normal_k": 48}},
    "meshlab_apss_mc": {0.003: {"filterscale": 4.0}, 0.01: {"filterscale": 4.0, "normal_k": 48}},
}


def preset_params(method: str, noise: float) -> dict:
    """The preset of ``method`` whose noise level is nearest (in log scale) to ``noise``
    (fraction of the bounding-box diagonal); ``{}`` for a method without presets."""
    table = PRESETS.get(method)
    if not table or noise is None or noise <= 0:
        return {}
    level = min(table, key=lambda n: abs(np.log(n) - np.log(noise)))
    return dict(table[level])
