"""Named tolerances, each with its unit and the reason for its value.

Stages import these instead of writing numbers inline, so a tolerance is changed in one place.
"""

# Rigid transforms read from files: |R^T R - I| and |det R - 1| allowed (float text rounding in
# 7-Scenes/ScanNet pose files reaches ~1e-5; a real scaling or shear is far larger).
POSE_ORTHONORMAL_TOL = 1e-3
