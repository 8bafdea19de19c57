"""The ``meshprep`` command line: inspect, repair, simplify, solid, proxy.

Exit codes: 0 ok, 1 the mesh could not be repaired / made solid, 2 usage error or unreadable input.
Errors are one line naming the file and the fix.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from meshprep import constants
from meshprep.errors import InputError, MeshprepError, RepairError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="meshprep",
        description="Repair, simplify, make solids and collision proxies of triangle meshes "
                    "(scans and object models). Every command except inspect writes a JSON report "
                    "(default OUT.report.json).")
    p.add_argument("-v", "--verbose", action="store_true", help="log progress to stderr")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    s = sub.add_parser("inspect", help="counts, bounds, units guess, holes, non-manifold elements",
                       description="Print mesh statistics and defects.")
    s.add_argument("mesh", help="mesh file (.ply .obj .off .stl .gltf .glb ...)")
    s.add_argument("--json", action="store_true", help="print JSON instead of text")
    s.add_argument("--self-intersections", choices=("auto", "yes", "no"), default="auto",
                   help=f"count self-intersecting faces (auto: up to "
                        f"{constants.SELF_INTERSECTION_MAX_FACES:,} faces)")

    s = sub.add_parser("repair", help="clean, drop junk, fix non-manifold, close holes, orient",
                       description="Repair a mesh (see meshprep.repair). Objects must end watertight "
                                   "and manifold; scans manifold with small holes closed.")
    s.add_argument("input")
    s.add_argument("output", help="output mesh (.ply .obj .off .stl)")
    s.add_argument("--kind", choices=("auto", "object", "scan"), default="auto",
                   help="object: close every hole; scan: close small holes only (default: auto)")
    s.add_argument("--cameras", help="camera positions (.npy/.txt: (N,3) or (N,4,4) camera-to-world) "
                                     "to orient a scan towards the free space")
    s.add_argument("--max-hole-edges", type=int, help="largest hole to close, in boundary edges")
    s.add_argument("--junk-diag", type=float, default=constants.JUNK_COMPONENT_DIAG_REL,
                   help="drop components smaller than this fraction of the bounding-box diagonal")
    s.add_argument("--junk-faces", type=int, default=constants.JUNK_COMPONENT_FACES,
                   help="drop components with fewer faces than this")
    s.add_argument("--report", help="JSON report path (default OUTPUT.report.json)")

    s = sub.add_parser("simplify", help="quadric edge collapse keeping colours, UVs and boundaries",
                       description="Simplify to a face count or to the smallest mesh within an error.")
    s.add_argument("input")
    s.add_argument("output")
    g = s.add_mutually_exclusive_group(required=True)
    g.add_argument("--target-faces", type=int, help="face count to reach")
    g.add_argument("--max-error", type=float, help="deviation bound in mesh units "
                                                   "(with --relative: fraction of the diagonal)")
    s.add_argument("--relative", action="store_true", help="--max-error is a fraction of the diagonal")
    s.add_argument("--error-stat", choices=("max", "p95", "mean"), default="max",
                   help="deviation statistic bounded by --max-error (default max)")
    s.add_argument("--boundary", choices=("weighted", "locked", "free"), default="weighted",
                   help="open borders: weighted (kept in place by extra quadrics; default), locked "
                        "(never moved or removed), free")
    s.add_argument("--seed", type=int, default=0, help="seed of the deviation sampling")
    s.add_argument("--workers", type=int, default=None,
                   help=f"decimation processes (default: 2 for meshes of "
                        f"{constants.PARALLEL_MIN_FACES:,}+ faces without UVs, else 1)")
    s.add_argument("--report", help="JSON report path (default OUTPUT.report.json)")

    s = sub.add_parser("solid", help="closed manifold solid with volume, com and inertia",
                       description="Repair as an object and make a closed manifold solid "
                                   "(manifold3d); the report holds mass properties and hull info.")
    s.add_argument("input")
    s.add_argument("output", help="output mesh (.ply .obj .off .stl)")
    s.add_argument("--density", type=float, default=1000.0, help="kg/m^3 (default 1000, water)")
    s.add_argument("--scale", type=float, default=1.0,
                   help="multiply coordinates first (0.001: millimetres to metres)")
    s.add_argument("--report", help="JSON report path (default OUTPUT.report.json)")

    s = sub.add_parser("proxy", help="collision proxy NPZ: room distance grid or object hulls+samples",
                       description="Room: unsigned (and with --cameras signed) distance grid. "
                                   "Object: hull, convex parts where needed, surface samples, mass "
                                   "properties.")
    s.add_argument("input")
    s.add_argument("output", help="output .npz")
    s.add_argument("--kind", choices=("auto", "room", "object"), default="auto")
    s.add_argument("--cameras", help="camera positions (rooms): orient the surface and add an sdf")
    s.add_argument("--spacing", type=float, default=constants.ROOM_SPACING_M, help="room grid step (m)")
    s.add_argument("--max-distance", type=float, default=constants.ROOM_MAX_DISTANCE_M,
                   help="room distances are clipped here (m)")
    s.add_argument("--density", type=float, default=1000.0, help="object density, kg/m^3")
    s.add_argument("--scale", type=float, default=1.0, help="multiply coordinates first")
    s.add_argument("--samples", type=int, default=constants.OBJECT_SAMPLES, help="object surface samples")
    s.add_argument("--seed", type=int, default=0, help="seed of the surface sampling")
    s.add_argument("--report", help="JSON report path (default OUTPUT.report.json)")
    return p


def _text(rep: dict) -> str:
    keys = ["file", "vertices", "faces", "components", "bounds", "diagonal", "units_guess",
            "watertight", "manifold", "oriented", "volume", "holes", "largest_hole_edges",
            "boundary_edges", "non_manifold_edges", "non_manifold_vertices",
            "inconsistent_orientation_edges", "degenerate_faces", "sliver_faces", "duplicate_faces",
            "duplicate_vertices", "unreferenced_vertices", "non_finite_vertices",
            "self_intersecting_faces", "vertex_colors", "uvs", "textures", "seconds"]
    return "\n".join(f"{k:32s} {rep.get(k)}" for k in keys)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 1 could not repair, 2 usage/unreadable input)."""
    parser = _parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # argparse: --help (0) or a usage error (2)
        return int(e.code or 0)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "inspect":
            from meshprep.io import dumps_json
            from meshprep.inspect import inspect

            si = {"auto": None, "yes": True, "no": False}[args.self_intersections]
            rep = inspect(args.mesh, self_intersections=si)
            sys.stdout.write(dumps_json(rep) if args.json else _text(rep) + "\n")
        elif args.command == "repair":
            from meshprep.repair import repair

            rep = repair(args.input, args.output, kind=args.kind, cameras=args.cameras,
                         report=args.report, max_hole_edges=args.max_hole_edges,
                         junk_diag_rel=args.junk_diag, junk_faces=args.junk_faces)
            a = rep["after"]
            sys.stdout.write(f"{args.output}: {a['faces']} faces, {rep['kind']}, watertight="
                             f"{a['watertight']}, manifold={a['manifold']}, {len(rep['changes'])} "
                             f"changes in {rep['seconds']} s\n")
        elif args.command == "simplify":
            from meshprep.simplify import simplify

            rep = simplify(args.input, args.output, target_faces=args.target_faces,
                           max_error=args.max_error, relative=args.relative,
                           error_stat=args.error_stat, boundary=args.boundary,
                           seed=args.seed, workers=args.workers, report=args.report)
            d = rep["deviation"]
            sys.stdout.write(f"{args.output}: {rep['before']['faces']} -> {rep['after']['faces']} "
                             f"faces, deviation mean {d['mean_rel']:.3%} p95 {d['p95_rel']:.3%} "
                             f"max {d['max_rel']:.3%} of the diagonal, {rep['seconds']} s\n")
        elif args.command == "solid":
            from meshprep.solid import solid

            rep = solid(args.input, args.output, density=args.density, scale=args.scale,
                        report=args.report)
            sys.stdout.write(f"{args.output}: volume {rep['volume']:.6g}, mass {rep['mass']:.6g}, "
                             f"com {[round(x, 6) for x in rep['com']]}, {rep['convex_parts']} convex "
                             f"parts, {rep['seconds']} s\n")
        elif args.command == "proxy":
            from meshprep.proxy import proxy

            rep = proxy(args.input, args.output, kind=args.kind, cameras=args.cameras,
                        spacing=args.spacing, max_distance=args.max_distance, density=args.density,
                        scale=args.scale, samples=args.samples, seed=args.seed, report=args.report)
            sys.stdout.write(f"{args.output}: {rep['kind']} proxy, {rep['seconds']} s\n")
    except RepairError as e:
        sys.stderr.write(f"meshprep {args.command}: error: {e}\n")
        return 1
    except InputError as e:
        sys.stderr.write(f"meshprep {args.command}: error: {e}\n")
        return 2
    except MeshprepError as e:  # pragma: no cover - every raise uses a subclass
        sys.stderr.write(f"meshprep {args.command}: error: {e}\n")
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
