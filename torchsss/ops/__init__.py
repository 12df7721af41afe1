"""Stateless, batched tensor ops. No meshes and no nn.Modules here."""

from torchsss.ops.reference import pairwise_distance, reference_radiosity
from torchsss.ops.sparse import SparsePattern, sparse_apply_t, sparse_pattern
from torchsss.ops.sv_conv import sv_conv2d, sv_conv2d_reference

__all__ = ["pairwise_distance", "reference_radiosity"]
__all__ += ["SparsePattern", "sparse_apply_t", "sparse_pattern", "sv_conv2d", "sv_conv2d_reference"]
