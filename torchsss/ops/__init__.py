"""Stateless, batched tensor ops. No meshes and no nn.Modules here."""

from torchsss.ops.reference import pairwise_distance, reference_radiosity

__all__ = ["pairwise_distance", "reference_radiosity"]
