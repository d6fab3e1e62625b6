"""The fitted material in renderers (docs/render.md): the staircase's 3-D reflectance as an RGL
measured material (`.bsdf`, read by Mitsuba's `measured` plugin and pbrt-v4), a Mitsuba 3 BSDF
plugin (`"type": "stairfit_staircase"`, `register_bsdf`), and renders of the photographed
specimen or of a printed object (`render_specimen`, `render_mesh`). Mitsuba is the optional
`render` extra (`pip install -e ".[render]"`); what needs it says so when it is missing.
"""

from ._fit import FitFolder as FitFolder
from ._fit import material_from_results as material_from_results
from ._fit import read_fit as read_fit
from ._material import BETA2_LIMITS_DEG as BETA2_LIMITS_DEG
from ._material import ArcGrid as ArcGrid
from ._material import Material as Material
from ._material import arc_grid as arc_grid
from ._material import density as density
from ._material import face_frame as face_frame
from ._mesh import Mesh as Mesh
from ._mesh import printed_parts as printed_parts
from ._mesh import read_obj as read_obj
from ._plugin import PLUGIN_NAME as PLUGIN_NAME
from ._plugin import register_bsdf as register_bsdf
from ._render import RenderOptions as RenderOptions
from ._render import parse_axis as parse_axis
from ._render import render_mesh as render_mesh
from ._render import render_specimen as render_specimen
from ._render import update_report as update_report
from ._rgl import DEFAULT_RESOLUTION as DEFAULT_RESOLUTION
from ._rgl import QUALITIES as QUALITIES
from ._rgl import Resolution as Resolution
from ._rgl import mitsuba_value as mitsuba_value
from ._rgl import tabulate as tabulate
from ._rgl import write_bsdf as write_bsdf
from ._sampling import Mixture as Mixture
from ._tensorfile import read_tensor_file as read_tensor_file
from ._tensorfile import tensor_bytes as tensor_bytes
