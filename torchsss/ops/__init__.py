"""Stateless, batched tensor ops. No meshes and no nn.Modules here."""

from torchsss.ops.caustic_splat import default_kernel_size, splat_caustics
from torchsss.ops.icdf import icdf_sample, icdf_sample_reference, pyramid_levels, sum_pyramid
from torchsss.ops.interp import barycentric_interpolate, barycentric_interpolate_reference
from torchsss.ops.newton_raphson import lookup_positions, newton_raphson_intersect
from torchsss.ops.reference import pairwise_distance, reference_radiosity
from torchsss.ops.refraction import reflect, refract
from torchsss.ops.sparse import SparsePattern, sparse_apply_t, sparse_pattern
from torchsss.ops.splat import splat_radiosity, splat_window_size
from torchsss.ops.sv_conv import sv_conv2d, sv_conv2d_planes, sv_conv2d_reference

__all__ = ["pairwise_distance", "reference_radiosity"]
__all__ += ["SparsePattern", "sparse_apply_t", "sparse_pattern", "sv_conv2d", "sv_conv2d_planes", "sv_conv2d_reference"]
__all__ += ["barycentric_interpolate", "barycentric_interpolate_reference"]
__all__ += ["icdf_sample", "icdf_sample_reference", "pyramid_levels", "sum_pyramid"]
__all__ += ["lookup_positions", "newton_raphson_intersect", "reflect", "refract"]
__all__ += ["default_kernel_size", "splat_caustics", "splat_radiosity", "splat_window_size"]
