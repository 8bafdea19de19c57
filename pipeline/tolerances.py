"""Named tolerances, each with its unit and the reason for its value.

Stages import these instead of writing numbers inline, so a tolerance is changed in one place.
"""

# Rotations read from files (scan pose files, poses files): up to this |R^T R - I| and |det R - 1| they
# are taken as rotations and replaced by the nearest one (SVD). Text rounding in 7-Scenes/ScanNet pose
# files reaches ~1e-5 and real annotations such as BOP ground truth ~2e-3; a scale or shear is far larger.
POSE_ORTHONORMAL_TOL = 1e-2

# Physics (issue 7): a box resting on a plane sits at its half extent within this (metres); soft
# MuJoCo-style contacts sink ~0.3 mm under their own weight at the default solimp/solref.
PHYS_REST_HEIGHT_TOL = 1e-3

# Physics vs MuJoCo rest poses (issue 7): position (m) and orientation (degrees) agreement required.
PHYS_MUJOCO_POS_TOL = 2e-3
PHYS_MUJOCO_ANGLE_TOL_DEG = 2.0

# Raster passes against an independent ray caster on the same posed meshes (issue 8): both sample the
# exact pixel centres, so only pixels whose centre lies within float rounding of an edge may differ.
RASTER_MASK_IOU_MIN = 0.995
# Median |raster depth - ray-cast depth| in metres: the 24-bit depth buffer resolves ~0.1 mm at 4 m
# with znear = 1 cm; 1 mm leaves room for float32 vertex transforms.
RASTER_DEPTH_MEDIAN_M = 1e-3

# Frame selection (issue 6): a frame whose gray-level std at the 320-px work resolution is below this
# (gray levels, 0..255) has no detail that blur could remove (a blank wall, a lens cap): it is kept as
# "textureless" and never used as a sharpness reference. 2 levels is just above 8-bit sensor noise.
SELECT_TEXTURELESS_STD = 2.0

# Ingest: a scan mesh is in the poses' units and frame when some camera sees at least this share of its
# vertices in its image within this range of depths (metres). A room scan's cameras see 20-60 % of the
# room each; a tabletop or one-view capture need not enclose its cameras but is seen by them; a mesh in
# millimetres (1000x too far) or another frame is seen by none.
MESH_SEEN_MIN_SHARE = 0.01
MESH_SEEN_DEPTH_M = (0.05, 50.0)

# Ingest: object models whose diameter falls outside this range (metres) after unit conversion get a
# warning naming the assumed unit (a 1 mm or 10 m "object" almost always means a wrong unit).
OBJECT_DIAMETER_PLAUSIBLE_M = (0.005, 3.0)

# Path tracer (issue 9). White furnace: an albedo-1 surface in uniform unit radiance must render 1; the
# issue's acceptance figure (0.5 %), loose enough for float32 shading and a few samples lost where an
# interpolated normal sends a ray under its facet, tight enough to catch a missing cos/pi or pdf term.
TRACE_FURNACE_REL_TOL = 0.005
# Against Mitsuba 3 on the three reference scenes: relative RMSE over object pixels (noise of both
# renderers at 2048 spp included, ~1.5 % measured) and relative mean bias (systematic part alone).
TRACE_MITSUBA_REL_RMSE_MAX = 0.02
TRACE_MITSUBA_REL_BIAS_MAX = 0.005
# The default object material (metallic 0, roughness 0.5, specular 1) against Mitsuba's `principled`: the
# issue's figure. Glossy highlights make both renderers noisier than the Lambert scenes: 1.4-1.6 % measured
# at 4096 spp each (0.8 % at 8192 / 16384 spp, bias under 0.1 %); the bias bound is the one above.
TRACE_MITSUBA_PRINCIPLED_REL_RMSE_MAX = 0.03
# Ray origins are moved this far (metres) off the surface along the geometric normal: ~100x the float32
# spacing of coordinates within 10 m of the origin, far below any feature of a 2 cm-voxel room scan.
TRACE_RAY_EPS_M = 1e-4

# Synthetic scans (issue 4), traced photo mode: mean linear brightness of a traced photo over the raster
# photo of the same frame. Both use the scan's exposure (set from the raster light map); the raster
# stands in for inter-reflections with a uniform ambient term (room.ambient x AO), the tracer computes
# them, so traced photos come out brighter in bright open views (measured 1.08-1.38 on seed 0 at
# 160x120) and the band is wide; a missing exposure or a lost light would fall far outside it.
SYNTHSCAN_TRACED_RASTER_MEAN_RATIO = (0.8, 1.6)

# Visibility (issue 18): an object pixel is in mask_visib where its distance from the camera is at most
# this far beyond the dataset's depth (or the depth is missing): bop_toolkit's estimate_visib_mask_gt
# ("bop19") with the delta its calc_gt_info.py uses (15 mm), so bop_toolkit recomputes the same masks
# from what we write. It is below raster.fusion_tol_abs (20 mm), so an object the real depth hides stays
# hidden; resting objects' contact rims within 15 mm of the surface count as visible, as in BOP.
BOP_VISIB_DELTA_M = 0.015
