"""The torch twins of the compiled kernels, named after the ops they mirror.

Every op of the C++ and CUDA modules (dss/csrc/dss_cpu_bind.cpp, dss_cuda_bind.cpp) has its
twin here under the op's name without ``_forward`` / ``_backward``: readable torch that the
tests hold the kernels to, and what runs on the ``reference`` backend and on devices without a
kernel. A twin whose op has a hand-written ``_backward`` is differentiable, so autograd gives the
backward that the kernel writes by hand.

==========================================  =====================================================
kernel op                                   torch twin
==========================================  =====================================================
``project_splats_forward`` / ``_backward``  :func:`project_splats` (stage 1)
``tangent_planes_forward``                  :func:`tangent_planes` (the visibility gradient's depths)
``rasterize_forward``                       :func:`rasterize` (the cache), :func:`blend_cached` (its image)
``blend_backward``                          :func:`blend` (Eq. sumI, differentiable in the splats)
``visibility_backward``                     :func:`visibility_backward` (Eqs. gradcase, filteredG)
``sun_shade_forward`` / ``_backward``       :func:`sun_shade`
``local_frames_forward``                    :func:`local_frames` (the regularisers' weighted PCA)
``neighbor_diff_forward`` / ``_backward``   :func:`neighbor_diff`
``knn_grid``                                :func:`knn_grid` (brute force, the same answer)
``morton_order``                            :func:`morton_order`
==========================================  =====================================================

``smape_sum`` is the fast path of :func:`dss.losses.smape_loss`, whose torch expression is its
twin (the loss takes masks and reductions the kernel does not). :data:`TWINS` is this table;
``tests/test_reference_layout.py`` checks it against the kernels' bindings. Where the kernels
run and how their autograd Functions call them: :mod:`dss.autograd`.
"""

from .blending import blend
from .frames import local_frames, neighbor_diff
from .neighbors import knn_grid
from .ordering import morton_codes, morton_order
from .projection import project_splats, tangent_planes
from .rasterization import bbox, blend_cached, rasterize, splat_weight
from .shading import sun_shade
from .visibility import visibility_backward

__all__ = ["project_splats", "tangent_planes", "rasterize", "blend_cached", "blend", "visibility_backward",
           "sun_shade", "local_frames", "neighbor_diff", "knn_grid", "morton_order", "morton_codes", "bbox",
           "splat_weight", "TWINS"]

#: kernel op -> the name of its torch twin in this package (None: no twin, with why)
TWINS: dict[str, str | None] = {
    "project_splats_forward": "project_splats",
    "project_splats_backward": "project_splats",
    "tangent_planes_forward": "tangent_planes",
    "rasterize_forward": "rasterize",
    "blend_backward": "blend",
    "visibility_backward": "visibility_backward",
    "sun_shade_forward": "sun_shade",
    "sun_shade_backward": "sun_shade",
    "local_frames_forward": "local_frames",
    "neighbor_diff_forward": "neighbor_diff",
    "neighbor_diff_backward": "neighbor_diff",
    "knn_grid": "knn_grid",
    "morton_order": "morton_order",
    "smape_sum": None,  # dss.losses.smape_loss
    # the kernels' own controls, no computation to mirror
    "splat_exp": None, "empty_cache": None, "set_vector_path": None, "vector_path_available": None,
    "set_vector_level": None, "vector_level": None, "max_vector_level": None,
}
