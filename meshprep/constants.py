"""Named tolerances and defaults, each with its unit and the reason for its value.

Lengths marked "relative" are fractions of the mesh's bounding-box diagonal, so the same rule works
for a model in millimetres and a room in metres.
"""

# A face is degenerate (zero-area) when its area is below this fraction of diag**2. float64 cross
# products of centred coordinates are exact to ~1e-16 relative; 1e-14 leaves head-room while any
# real sliver of a scan (area ~ (1e-4 diag)**2 = 1e-8 diag**2) stays far above it.
DEGENERATE_AREA_REL = 1e-14

# Vertices closer than this fraction of diag are merged as duplicates during repair. Exporters that
# write one vertex per corner repeat coordinates bit for bit; 1e-9 catches float32 round-off only.
MERGE_DISTANCE_REL = 1e-9

# Connected components whose bounding-box diagonal is below this fraction of the whole mesh's are
# floating junk (TSDF specks, scanner noise) and are removed. 1 % of a 7 m room is 7 cm: specks are
# smaller, furniture parts that are real are larger and almost always connected to something.
JUNK_COMPONENT_DIAG_REL = 0.01

# Components with fewer faces than this are removed whatever their size (lone triangles, fans).
JUNK_COMPONENT_FACES = 10

# Largest hole (boundary edges) closed on an object: objects must end closed, so this is large; holes
# bigger than this are an open shell that hole filling would only hide.
OBJECT_MAX_HOLE_EDGES = 100_000

# Largest hole (boundary edges) closed on a scan: only small dropouts; large openings (windows,
# unscanned walls) are the scan's real boundary and must stay open.
SCAN_MAX_HOLE_EDGES = 100

# A repair repeats its passes until nothing changes, at most this many times (non-manifold fixes can
# open holes that the next pass closes; two passes settle every corpus case).
REPAIR_MAX_PASSES = 4

# Self-intersection test (O(F log F) but with a large constant in MeshLab) only below this many
# faces; above it `inspect` reports null ("not checked").
SELF_INTERSECTION_MAX_FACES = 300_000

# Surface samples per mesh side for deviation (Hausdorff) measurements: p95 is stable to ~1 % of its
# value at 100k samples on the room mesh.
DEVIATION_SAMPLES = 100_000

# --max-error search: face counts are tried until the bracket is within this fraction.
MAX_ERROR_SEARCH_REL = 0.05

# Convex decomposition: a piece is accepted when its hull's mean gap (hull volume - piece volume,
# divided by hull area; a length) is below this fraction of the diagonal of the whole object.
CONCAVITY_TOL_REL = 0.01

# Convex decomposition stops after this many pieces (physics cost grows with the count).
MAX_CONVEX_PARTS = 32

# Room proxy defaults, in metres (room scans are metric): a 2 cm grid matches TSDF voxel size;
# distances beyond 0.3 m are clipped (no drop starts closer than that to a surface, and physics only
# needs precise values near contact).
ROOM_SPACING_M = 0.02
ROOM_MAX_DISTANCE_M = 0.30

# Exact point-to-triangle distances are computed within this many voxels of a surface sample; farther
# voxels get the grid (EDT) distance, which is within sqrt(3)/2 voxel of the truth.
ROOM_EXACT_BAND_VOXELS = 4

# Room grids above this many voxels are refused (memory: 4 bytes x 3 arrays each); the message
# names --spacing.
ROOM_MAX_VOXELS = 200_000_000

# Free-space flood fill: voxels within this distance (metres) of the surface block the flood, so
# scan holes narrower than twice this do not leak the sign to the far side.
ROOM_SIGN_BARRIER_M = 0.05

# Object proxy surface samples (points on the surface with normals).
OBJECT_SAMPLES = 2048

# Relative tolerance the mass-property tests hold analytic solids to (issue requirement).
MASS_PROPERTIES_REL_TOL = 0.005

# Non-manifold vertex split: the copies move this fraction of the mean edge length towards their fan,
# so the exact-duplicate pass does not weld them back (0 makes repair cycle between the two).
SPLIT_VERTEX_DISPLACEMENT = 0.01

# Room proxy grids extend this far (metres) beyond the mesh's bounding box on every side.
ROOM_PAD_M = 0.10

# Room sdf: the sign of a voxel is trusted when the direction to its closest surface point is within
# acos(0.3) ~ 72 degrees of that face's normal; beside open borders it is not (the point is "next to"
# the surface, neither in front nor behind).
ROOM_SIGN_MIN_COS = 0.3

# Simplification of meshes with at least this many faces runs in two processes (slabs with fixed
# cuts): decimation is single-threaded and dominates the time of a 2M-face repair + simplify.
PARALLEL_MIN_FACES = 400_000

# Weight of the border-plane quadrics in simplification ("weighted" boundary mode). On the
# 7-Scenes room at 10x/20x/50x, weight 3 with free borders gave p95 0.07/0.19/0.65 % of the
# diagonal; locking the borders stalled at ~12k faces with 1.8 % (folds next to locked borders).
BOUNDARY_QUADRIC_WEIGHT = 3.0
