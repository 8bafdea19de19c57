"""Procedural synthetic room scans with exact ground truth, written in real scan layouts.

Public API (imports stay light; the renderer loads pyrender only when a scan is made)::

    from pipeline.synthscan import make_scan, builtin_scan
    make_scan("out/scan", layout="scannet", seed=3, width=320, height=240, frames=20)
    builtin_scan("tiny", "out/tiny")      # presets: "demo" (640x480, 50 frames), "tiny" (160x120, 8)

Modules: ``room`` (geometry, materials, lights), ``textures``, ``lighting`` (area-light irradiance and
shadows), ``trajectory`` (handheld walk, intrinsics, exposure paths), ``render`` (photo modes behind
``PhotoRenderer``), ``degrade`` (sensor noise, blur, depth errors), ``scanmesh`` (the scanner's mesh),
``writers`` (the four layouts), ``contact`` (contact sheet), ``generate`` (``make_scan``), ``cli``.
"""

from __future__ import annotations

from pipeline.synthscan.generate import LAYOUTS, PRESETS, builtin_scan, make_scan

__all__ = ["LAYOUTS", "PRESETS", "builtin_scan", "make_scan"]
