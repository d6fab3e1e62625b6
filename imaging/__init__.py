"""RAW photographs to calibrated per-wedge radiance, with honest uncertainties.

Decoding without demosaic (rawpy), ROIs from pixel polygons or ArUco markers (OpenCV), per-ROI
and per-channel mean relative radiance with block standard errors, a cached CSV table, preview
PNGs, and a generator of synthetic RAW photos (`stairfit.imaging.synthetic`). This package
depends on no other stairfit package. Pixel and unit conventions: docs/imaging.md.

The usual entry point::

    from stairfit import imaging

    specs = [imaging.PhotoSpec("a.dng", rois={"w30": [(10, 10), (200, 10), (200, 150)]})]
    table = imaging.measure_photos(specs, imaging.ExtractionSettings(), cache="m.csv")
"""

from . import synthetic as synthetic
from ._calibration import Calibration as Calibration
from ._calibration import CalibrationFile as CalibrationFile
from ._calibration import CalibrationSpec as CalibrationSpec
from ._calibration import DarkFrame as DarkFrame
from ._calibration import FlatField as FlatField
from ._calibration import build_calibration as build_calibration
from ._calibration import calibration_spec as calibration_spec
from ._camera_tags import CameraTags as CameraTags
from ._camera_tags import read_camera_tags as read_camera_tags
from ._decode import CHANNELS as CHANNELS
from ._decode import RawFrame as RawFrame
from ._decode import decode_raw as decode_raw
from ._decode import file_sha256 as file_sha256
from ._errors import ImagingError as ImagingError
from ._errors import ImagingWarning as ImagingWarning
from ._errors import PhotosFailedError as PhotosFailedError
from ._exposure import Exposure as Exposure
from ._exposure import resolve_exposure as resolve_exposure
from ._extract import ChannelStats as ChannelStats
from ._extract import ExtractionSettings as ExtractionSettings
from ._extract import roi_channel_stats as roi_channel_stats
from ._hdr import BracketMember as BracketMember
from ._hdr import Radiometry as Radiometry
from ._hdr import prepare_radiometry as prepare_radiometry
from ._markers import ARUCO_DICTIONARIES as ARUCO_DICTIONARIES
from ._markers import LEGACY_DETECTOR as LEGACY_DETECTOR
from ._markers import TONE_MAPS as TONE_MAPS
from ._markers import DetectorSettings as DetectorSettings
from ._markers import MarkerDetection as MarkerDetection
from ._markers import MarkerLayout as MarkerLayout
from ._markers import Placement as Placement
from ._markers import binned_linear as binned_linear
from ._markers import detect_markers as detect_markers
from ._markers import fit_placement as fit_placement
from ._pipeline import TABLE_VERSION as TABLE_VERSION
from ._pipeline import FrameMeasurement as FrameMeasurement
from ._pipeline import PhotoSpec as PhotoSpec
from ._pipeline import cache_key as cache_key
from ._pipeline import decode_view as decode_view
from ._pipeline import measure_frame as measure_frame
from ._pipeline import measure_photo as measure_photo
from ._pipeline import measure_photos as measure_photos
from ._pipeline import place_faces as place_faces
from ._pipeline import preview_path as preview_path
from ._pipeline import summarise_failures as summarise_failures
from ._placement import MIN_DETECTABLE_CELL_PX as MIN_DETECTABLE_CELL_PX
from ._placement import PLACEMENT_MODELS as PLACEMENT_MODELS
from ._placement import CameraPose as CameraPose
from ._placement import PinholeCamera as PinholeCamera
from ._placement import face_outline_3d as face_outline_3d
from ._placement import face_polygon as face_polygon
from ._placement import face_view_deg as face_view_deg
from ._placement import fit_camera_pose as fit_camera_pose
from ._placement import pixel_view_deg as pixel_view_deg
from ._placement import pixels_on_face as pixels_on_face
from ._placement import roi_face_points as roi_face_points
from ._placement import roi_view_half_width_deg as roi_view_half_width_deg
from ._placement import view_parallax_deg as view_parallax_deg
from ._preview import render_preview as render_preview
from ._preview import write_preview as write_preview
from ._roi import MAX_ERODE_PX as MAX_ERODE_PX
from ._roi import Polygon as Polygon
from ._roi import RoiMask as RoiMask
from ._roi import roi_mask as roi_mask
from ._table import COLUMNS as COLUMNS
from ._table import MeasurementRow as MeasurementRow
from ._table import MeasurementTable as MeasurementTable
