"""Physics shared by every method: the dipole profile, Fresnel terms, budgets, presets, lookup tables.

Pure functions of tensors; no meshes, no nn.Modules. Lengths in mm, coefficients in mm^-1.
"""

from torchsss.physics.budget import (
    chang_rp,
    chang_weights,
    profile_tail_fraction,
    r_max,
    splat_alias_error,
    splat_count,
    splat_overlap,
    splat_spacing,
)
from torchsss.physics.burley import burley_cumulative, burley_params_from_dipole, burley_r_max, burley_rd
from torchsss.physics.dipole import (
    DipoleTerms,
    dipole_cumulative,
    dipole_rd,
    dipole_rd_shah,
    dipole_spectrum,
    dipole_terms,
    total_diffuse_reflectance,
)
from torchsss.physics.fresnel import (
    FRESNEL_MODES,
    check_fresnel,
    diffuse_fresnel_reflectance,
    dipole_boundary_a,
    exit_radiance,
    fresnel_reflectance,
    fresnel_transmittance,
    schlick_reflectance,
    schlick_transmittance,
    transmittance,
)
from torchsss.physics.lut import (
    ProfileTable,
    build_profile_table,
    fitted_profile_table,
    lookup_profile_table,
    profile_table_error,
)
from torchsss.physics.materials import PROFILES, Material, MaterialPreset, preset, preset_names
from torchsss.physics.sh import SH_COEFFS, fresnel_cosine_zonal, project_sh, sh_basis, sh_irradiance, sphere_quadrature

__all__ = [
    "FRESNEL_MODES",
    "PROFILES",
    "SH_COEFFS",
    "DipoleTerms",
    "Material",
    "MaterialPreset",
    "ProfileTable",
    "build_profile_table",
    "burley_cumulative",
    "burley_params_from_dipole",
    "burley_r_max",
    "burley_rd",
    "chang_rp",
    "chang_weights",
    "check_fresnel",
    "diffuse_fresnel_reflectance",
    "dipole_boundary_a",
    "dipole_cumulative",
    "dipole_rd",
    "dipole_rd_shah",
    "dipole_spectrum",
    "dipole_terms",
    "exit_radiance",
    "fitted_profile_table",
    "fresnel_cosine_zonal",
    "fresnel_reflectance",
    "fresnel_transmittance",
    "lookup_profile_table",
    "preset",
    "preset_names",
    "profile_table_error",
    "profile_tail_fraction",
    "project_sh",
    "r_max",
    "schlick_reflectance",
    "schlick_transmittance",
    "sh_basis",
    "sh_irradiance",
    "sphere_quadrature",
    "splat_alias_error",
    "splat_count",
    "splat_overlap",
    "splat_spacing",
    "total_diffuse_reflectance",
    "transmittance",
]
