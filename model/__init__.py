"""The staircase BRDF of FDM-printed surfaces: a pure, differentiable JAX forward model.

Conventions (angles, facets, units) are in docs/conventions.md and cited as [conventions §N].
"""

from ._brdf import brdf as brdf
from ._brdf import flat_reflectance as flat_reflectance
from ._broadening import hemisphere_gaussian as hemisphere_gaussian
from ._cell import Projections as Projections
from ._cell import UnitCell as UnitCell
from ._cell import facet_projections as facet_projections
from ._cell import unit_cell as unit_cell
from ._diffuse import diffuse_broadened as diffuse_broadened
from ._diffuse import diffuse_sharp as diffuse_sharp
from ._fresnel import SP as SP
from ._fresnel import fresnel_sp as fresnel_sp
from ._fresnel import fresnel_unpolarised as fresnel_unpolarised
from ._lobes import LOBE_NAMES as LOBE_NAMES
from ._lobes import Lobes as Lobes
from ._lobes import lobe_directions as lobe_directions
from ._lobes import lobe_fresnel as lobe_fresnel
from ._lobes import lobe_weight_kinks as lobe_weight_kinks
from ._lobes import lobe_weights as lobe_weights
from ._lobes import sharp_lobes as sharp_lobes
from ._measurement import Aperture as Aperture
from ._measurement import band_density as band_density
from ._measurement import band_kernel as band_kernel
from ._measurement import band_ratio as band_ratio
from ._measurement import light_nodes as light_nodes
from ._measurement import node_angles as node_angles
from ._measurement import radiance as radiance
from ._measurement import view_conversion as view_conversion
from .materials import MATERIALS as MATERIALS
from .materials import get_material as get_material
from .materials import refractive_index as refractive_index
from .spectral import ChannelWeights as ChannelWeights
from .spectral import channel_weights as channel_weights
from .spectral import xyz_weights as xyz_weights

# isort: split
# The rounded-edge model (issue 5; docs/rounded.md), appended after the exports above.
from ._rounded import ARC_LOBE_NAMES as ARC_LOBE_NAMES
from ._rounded import PATH_NAMES as PATH_NAMES
from ._rounded import ROUNDED_RESOLUTION as ROUNDED_RESOLUTION
from ._rounded import RoundedGeometry as RoundedGeometry
from ._rounded import RoundedPaths as RoundedPaths
from ._rounded import RoundedStructure as RoundedStructure
from ._rounded import arc_single_seen as arc_single_seen
from ._rounded import brdf_rounded as brdf_rounded
from ._rounded import brdf_rounded_from_geometry as brdf_rounded_from_geometry
from ._rounded import check_edge_radius as check_edge_radius
from ._rounded import max_edge_radius as max_edge_radius
from ._rounded import rounded_binned as rounded_binned
from ._rounded import rounded_delta_weight as rounded_delta_weight
from ._rounded import rounded_geometry as rounded_geometry
from ._rounded import rounded_paths as rounded_paths
from ._rounded import rounded_structure as rounded_structure
from ._rounded import rounded_total as rounded_total

# isort: split
# Concave fillets (issue 15; docs/rounded.md §1, §11), appended after the rounded exports.
from ._fillet import FILLET_BOUNCES as FILLET_BOUNCES
from ._fillet import FILLET_RAYS as FILLET_RAYS
from ._fillet import FilletGeometry as FilletGeometry
from ._fillet import FilletRays as FilletRays
from ._fillet import brdf_filleted as brdf_filleted
from ._fillet import brdf_filleted_from_geometry as brdf_filleted_from_geometry
from ._fillet import check_fillet_radius as check_fillet_radius
from ._fillet import difference_scale as difference_scale
from ._fillet import fillet_bounce_bound as fillet_bounce_bound
from ._fillet import fillet_difference_points as fillet_difference_points
from ._fillet import fillet_geometry as fillet_geometry
from ._fillet import fillet_ray_power as fillet_ray_power
from ._fillet import fillet_rays as fillet_rays
from ._fillet import filleted_binned as filleted_binned
from ._fillet import filleted_total as filleted_total
from ._fillet import max_fillet_radius as max_fillet_radius
from ._fillet import split_rays as split_rays

# isort: split
# Any pair of 3-D directions, Gaussian or microfacet facets (issue 40; docs/model.md §7).
from ._lab import LAB_KERNELS as LAB_KERNELS
from ._lab import PLATE_WIDTH_FLOOR_RAD as PLATE_WIDTH_FLOOR_RAD
from ._lab import InPlane as InPlane
from ._lab import Lobes3D as Lobes3D
from ._lab import RoughRetro as RoughRetro
from ._lab import face_direction as face_direction
from ._lab import facet_normals as facet_normals
from ._lab import lab_body as lab_body
from ._lab import lab_density_gaussian as lab_density_gaussian
from ._lab import lab_density_microfacet as lab_density_microfacet
from ._lab import lab_lobes as lab_lobes
from ._lab import line_gaussian as line_gaussian
from ._lab import lit_fractions as lit_fractions
from ._lab import lobe_fresnel_3d as lobe_fresnel_3d
from ._lab import plate_reflectance as plate_reflectance
from ._lab import projected_incidence as projected_incidence
from ._lab import projected_view as projected_view
from ._lab import retro_weight_rough as retro_weight_rough
from ._lab import rough_retro as rough_retro
from ._lab_rounded import ARC_BODY_NODES as ARC_BODY_NODES
from ._lab_rounded import ARC_SIGMA_PER_ALPHA as ARC_SIGMA_PER_ALPHA
from ._lab_rounded import arc_deflection as arc_deflection
from ._lab_rounded import arc_panels as arc_panels
from ._lab_rounded import arc_single as arc_single
from ._lab_rounded import lab_body_rounded as lab_body_rounded
from ._lab_rounded import lab_density_rounded as lab_density_rounded
from ._lab_rounded import rounded_arcs as rounded_arcs
from ._lab_rounded import rounded_flats as rounded_flats
from ._microfacet import DISTRIBUTIONS as DISTRIBUTIONS
from ._microfacet import ROUGHNESS_ANGLE_MAX_RAD as ROUGHNESS_ANGLE_MAX_RAD
from ._microfacet import ndf as ndf
from ._microfacet import roughness_alpha as roughness_alpha
from ._microfacet import slope_cdf as slope_cdf
from ._microfacet import slope_marginal as slope_marginal
from ._microfacet import smith_g1 as smith_g1
from ._microfacet import smith_lambda as smith_lambda

# isort: split
# Gloss units (ISO 2813) of the staircase (issue 41; docs/gloss.md).
from ._gloss import GLOSS_ILLUMINANT as GLOSS_ILLUMINANT
from ._gloss import GLOSS_STANDARD_INDEX as GLOSS_STANDARD_INDEX
from ._gloss import GLOSS_STANDARD_WAVELENGTH_NM as GLOSS_STANDARD_WAVELENGTH_NM
from ._gloss import ISO2813_APERTURES as ISO2813_APERTURES
from ._gloss import RECEPTOR_NODES as RECEPTOR_NODES
from ._gloss import SOURCE_NODES as SOURCE_NODES
from ._gloss import Gloss as Gloss
from ._gloss import GlossAperture as GlossAperture
from ._gloss import GlossGeometry as GlossGeometry
from ._gloss import GlossSurface as GlossSurface
from ._gloss import gloss as gloss
from ._gloss import iso2813_geometry as iso2813_geometry
from ._gloss import luminous_rule as luminous_rule
