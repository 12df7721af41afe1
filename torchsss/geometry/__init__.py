"""Geometry: meshes in millimetres, texture atlas, rasterizer, cameras, lights, shadows, G-buffers.

No nn.Modules here (DESIGN.md §3): these are the build-once inputs of every method - a mesh at its real size,
an atlas whose texels know their surface point, image-space G-buffers from the camera's and the light's view,
and irradiance with Fresnel and shadows. All lengths are millimetres.
"""

from torchsss.geometry.atlas import Atlas, build_atlas, parameterize
from torchsss.geometry.camera import Camera, look_at, orthographic, perspective, pixel_centers_ndc, transform_points
from torchsss.geometry.coherence import AttachedSamples, attach_light_view, coherent_light_samples
from torchsss.geometry.environment import EnvironmentLight, environment_irradiance
from torchsss.geometry.gbuffer import GBuffer, LightView, bend_towards_viewer, camera_gbuffer, light_view, view_cosine
from torchsss.geometry.lensch import (
    BlendWeights,
    DenseThroughput,
    HatQuadrature,
    LocalKernelGeometry,
    Throughput,
    VertexWeights,
    blending_weights,
    build_dense_throughput,
    build_throughput,
    hat_quadrature,
    local_kernel_geometry,
    plan_kernel_size,
    plan_lensch,
    throughput_layout,
    throughput_values,
    vertex_weights,
)
from torchsss.geometry.lights import (
    DirectionalLight,
    Light,
    PointLight,
    SpotLight,
    incident_light,
    light_from_dict,
    surface_irradiance,
)
from torchsss.geometry.loading import builtin_mesh_names, builtin_mesh_path, load_mesh
from torchsss.geometry.mesh import (
    Mesh,
    MeshWarning,
    decimate,
    mesh_from_arrays,
    normalize_to_size,
    surface_deviation,
)
from torchsss.geometry.objects import merge_meshes, object_ids, object_masks
from torchsss.geometry.peel import EnvironmentSplats, axis_camera, environment_splats
from torchsss.geometry.procedural import plane, slab, sphere, torus
from torchsss.geometry.raster import Raster, depth_peel, interpolate, rasterize, rasterize_uv
from torchsss.geometry.refine import feature_edges, refine_creases
from torchsss.geometry.sampling import SurfaceSamples, subdivision_barycentrics, surface_samples
from torchsss.geometry.shadow import ShadowMap, bounding_sphere, build_shadow_map, light_camera, shadow_visibility
from torchsss.geometry.visibility import point_inside, ray_visibility

__all__ = [
    "Atlas",
    "AttachedSamples",
    "BlendWeights",
    "Camera",
    "DenseThroughput",
    "DirectionalLight",
    "EnvironmentLight",
    "EnvironmentSplats",
    "GBuffer",
    "HatQuadrature",
    "Light",
    "LightView",
    "LocalKernelGeometry",
    "Mesh",
    "MeshWarning",
    "PointLight",
    "Raster",
    "ShadowMap",
    "SpotLight",
    "SurfaceSamples",
    "Throughput",
    "VertexWeights",
    "attach_light_view",
    "axis_camera",
    "bend_towards_viewer",
    "blending_weights",
    "bounding_sphere",
    "build_atlas",
    "build_dense_throughput",
    "build_shadow_map",
    "build_throughput",
    "builtin_mesh_names",
    "builtin_mesh_path",
    "camera_gbuffer",
    "coherent_light_samples",
    "decimate",
    "depth_peel",
    "environment_irradiance",
    "environment_splats",
    "feature_edges",
    "hat_quadrature",
    "incident_light",
    "interpolate",
    "light_camera",
    "light_from_dict",
    "light_view",
    "load_mesh",
    "local_kernel_geometry",
    "look_at",
    "merge_meshes",
    "mesh_from_arrays",
    "normalize_to_size",
    "object_ids",
    "object_masks",
    "orthographic",
    "parameterize",
    "perspective",
    "pixel_centers_ndc",
    "plan_kernel_size",
    "plan_lensch",
    "plane",
    "point_inside",
    "rasterize",
    "rasterize_uv",
    "ray_visibility",
    "refine_creases",
    "shadow_visibility",
    "slab",
    "sphere",
    "subdivision_barycentrics",
    "surface_deviation",
    "surface_irradiance",
    "surface_samples",
    "throughput_layout",
    "throughput_values",
    "torus",
    "transform_points",
    "vertex_weights",
    "view_cosine",
]
