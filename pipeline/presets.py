"""Quality presets: named sets of config defaults (``run.preset``).

A preset only changes defaults: any key the config file or ``--set`` gives explicitly wins. ``default``
is the config dataclasses' own defaults. The speed/quality trade-off of each preset is measured by
``bench/e2e.py``.
"""

from __future__ import annotations

PRESETS: dict[str, dict[str, dict]] = {
    # Fewest samples that still give a usable image; for quick looks and for tests.
    "fast": {
        "trace": {"spp": 4, "spp_min": 2, "max_depth": 2, "ao_samples": 1, "shadow_samples": 8, "photo_frames": 8},
    },
    "default": {},
    # Reference-like quality: more samples, deeper paths, lower noise target.
    "high": {
        "trace": {"spp": 64, "spp_min": 16, "max_depth": 5, "noise_target": 0.01, "ao_samples": 4,
                  "shadow_samples": 64, "shadow_min_effect": 0.01, "photo_frames": 64},
    },
}
