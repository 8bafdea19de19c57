"""The light fit's settings: :class:`FitSettings`, which the trace stage fills from its TraceConfig."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.trace.lightfit.capture import AVERAGE_ALBEDO

# albedo of a ceiling no photo saw: white paint, the surface a room most often leaves white (EN 12464-1
# recommends 0.7-0.9 for a ceiling)
CEILING_ALBEDO = 0.8


@dataclass(frozen=True)
class FitSettings:
    """Knobs of :func:`~pipeline.trace.lightfit.fit_room_lights` (the trace stage fills them from TraceConfig)."""

    points: int = 16000         # room points the fit uses at most (every other one to find where the light is)
    gather_rays: int = 64       # hemisphere rays per point for the known irradiance
    emitter_samples: int = 2    # area samples per (point, unknown) pair
    cell: float = 0.4           # metres, size of the closing box's cells
    albedo_cell: float = 0.5    # metres, size of an albedo patch
    albedo_group: float = 0.03  # cells whose photo chromaticity falls in one bin this wide share an albedo (0 = off)
    stride: int = 8             # photo pixels between grid rays
    threshold: int = 250        # 8-bit level at which a channel counts as clipped
    min_share: float = 0.5      # share of clipped observations that makes a mesh vertex an emitter
    sparsity: float = 0.4       # L1 weight on emission (columns normalised; relative to the data term's scale)
    level_tolerance: float = 0.05  # stage 1: the highest albedo level whose objective is within this share of the best
    support_share: float = 0.999   # stages 2 and 3: the emitters carrying this share of the power emit
    max_emitters: int = 24      # stage 2: at most this many unknown cells emit (0 = no second stage)
    refine: float = 0.1         # stage 3: metres, size of the lamps the emitting cells are refined into (0 = off)
    polish: int = 60            # stage 3: objective evaluations placing and sizing each cluster of lamps (0 = off)
    radiance_scale: float = 1.0  # the trace stage's: radiance = this x linear colour
    white_prior: float = 0.1    # last stage without white_patch: pull of the emitters' colour toward white (0 = off)
    white_patch: float = 1.0    # last stage: pull of the brightest surfaces' albedo toward grey (0 = white_prior's)
    ceiling_albedo: float = CEILING_ALBEDO  # the unseen ceiling's albedo, white (0 = the upper walls', as the sides)
    known_complete: bool = False  # the known lights are every light: the fit adds none (trace.lights_complete)
    capture_views: int = 3      # fewer photos than this: the light's level and colour from the camera (``capture``)
    capture_albedo: float = AVERAGE_ALBEDO  # then: the photographed surfaces' mean albedo (luminance, linear)
    edge_colour: bool = True    # the lights the photos saw clipped take the colour of the pixels their edges cover
