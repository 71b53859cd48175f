"""Command line: mls-mpm run | morph | check | render | bench. `main(argv) -> int`; Taichi starts only inside a command.

Exit codes: 0 done; 1 a simulation that went wrong, or `check` beyond its tolerances; 2 a bad command line or
bad input (one line `mls-mpm: error: ...`); 130 and 143 stopped by SIGINT (Ctrl-C) and SIGTERM, after keeping
what was finished. Nothing heavy is imported before `main` runs, so that Ctrl-C at any time gives one line.
"""
import argparse
import signal
import sys

USAGE_ERRORS = 2
SIGNAL_EXIT = {signal.SIGINT: 130, signal.SIGTERM: 143}  # 128 + the signal's number


class StopFlag:
    """Set by SIGINT/SIGTERM; the optimizer checkpoints and returns, rendering raises Interrupted, when it sees it."""

    def __init__(self):
        self.signal = None

    def __call__(self):
        return self.signal is not None

    def install(self):
        """Install the handlers; returns a function that puts the previous ones back."""
        previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}

        def handler(signum, _frame):
            if self.signal is not None:  # a second Ctrl-C: stop now
                raise KeyboardInterrupt
            self.signal = signum
            print(f"\nmls-mpm: got signal {signum} ({signal.Signals(signum).name}); stopping after the current "
                  "step (a second signal stops at once)...", file=sys.stderr, flush=True)

        for sig in previous:
            signal.signal(sig, handler)
        return lambda: [signal.signal(sig, h) for sig, h in previous.items()]

    def exit_code(self):
        """130 after SIGINT, 143 after SIGTERM."""
        return SIGNAL_EXIT.get(self.signal, 130)


class Parser(argparse.ArgumentParser):
    """argparse whose errors are one line, `mls-mpm: error: <command>: <what is wrong>; see ... --help`, exit 2
    (argparse's own print the usage, then the error). --help is unchanged."""

    def error(self, message):
        command = self.prog.partition(" ")[2]
        where = f"{command}: " if command else ""
        self.exit(USAGE_ERRORS, f"mls-mpm: error: {where}{message}; see {self.prog} --help\n")


def integer(lo, hi=None, unit=""):
    """An option's type: an integer in [lo, hi] (hi None: no upper bound); argparse names the option."""
    bounds = f">= {lo}" if hi is None else f"from {lo} to {hi}"

    def parse(text):
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < lo or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"expected an integer {bounds}{unit}, got {text!r}")
        return value

    return parse


def positive(text):
    """An option's type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        value = None
    if value is None or not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def run_options(parser, what, command):
    """The options `run` and `morph` share: --set, --arch, --resume, --no-render, --quiet."""
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help=f"override {what} (repeatable)")
    parser.add_argument("--arch", choices=["cpu", "gpu"], help="override sim.arch")
    parser.add_argument("--resume", action="store_true", help=f"continue an interrupted {command} from its checkpoint")
    parser.add_argument("--no-render", action="store_true", help="skip frames, gif and sheet")
    parser.add_argument("--quiet", action="store_true", help="print only the final line")


def build_parser():
    from .export3d import MODES_3D
    from .scene import RENDER_MODES, RENDER_SIZE_MAX, RENDER_SIZE_MIN

    fmt = argparse.ArgumentDefaultsHelpFormatter
    p = Parser(prog="mls-mpm", formatter_class=fmt,
               description="Differentiable MLS-MPM shape morphing (thesis: M. Xu, 2020).")
    sub = p.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", formatter_class=fmt, help="optimize a scene and render its animation")
    run.add_argument("scene", help="scene file (TOML), see scenes/README.md")
    run.add_argument("--out", help="output folder (default: renders/<scene name>/)")
    run_options(run, "a scene key, e.g. --set sim.n_grid=128", "run")

    morph = sub.add_parser("morph", formatter_class=fmt,
                           help="morph one shape into another (2D images; 3D meshes, solids, extruded images): "
                                "settings chosen from the two shapes, no scene file")
    morph.add_argument("initial", help="the initial shape: an image (scenes/README.md, Shapes from images), or in 3D a "
                                       "mesh file, shape:NAME or extrude:IMAGE (scenes/README.md, 3D scenes)")
    morph.add_argument("target", help="the target shape, in the same forms")
    morph.add_argument("--out", help="output folder (default: renders/morph_<initial>_to_<target>/)")
    morph.add_argument("--quality", choices=["fast", "default", "best"], default="default",
                       help="fast: a 32^2 preview within ~30 s (3D: 24^3); default: 64^2 (3D: 32^3) within ~2 "
                            "minutes; best: the default's grid, no time budget (2D: two rounds of 800 iterations)")
    morph.add_argument("--seconds", type=positive, help="wall-clock budget of the optimization, compile included "
                                                        "(default: 25 fast, 105 default, none best; 3D: 120 fast and "
                                                        "default)")
    morph.add_argument("--loss", choices=["auto", "mass", "color"], default="auto",
                       help="auto: the colour loss when both images have more than one colour region, else "
                            "optimal transport + mass")
    morph.add_argument("--dim", type=int, choices=[2, 3],
                       help="2 or 3 (default: 3 when INITIAL or TARGET is a mesh, shape: or extrude:, else 2); "
                            "--dim 3 with a 2D image asks for extrude:IMAGE")
    morph.add_argument("--keep-position", action="store_true",
                       help="keep the target where its image puts it (default: moved onto the body's centre of "
                            "mass, which internal controls cannot move)")
    run_options(morph, "any chosen scene key, e.g. --set sim.steps=300", "morph")

    check = sub.add_parser("check", formatter_class=fmt,
                           help="compare the manual gradient with ti.ad.Tape and finite differences")
    check.add_argument("scene")
    check.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    check.add_argument("--steps", type=integer(2), default=12, help="steps of the reduced scene (>= 2)")
    check.add_argument("--particles", type=integer(1), default=300, help="particles kept (an even subsample)")
    check.add_argument("--tol-tape", type=positive, default=1e-6, help="largest relative error against Tape (> 0)")
    check.add_argument("--tol-fd", type=positive, default=1e-5, help="largest relative error against FD (> 0)")

    render = sub.add_parser("render", formatter_class=fmt, help="re-render a finished run from its result.npz")
    render.add_argument("dir", help="output folder of a finished run")
    render.add_argument("--mode", choices=RENDER_MODES + tuple(m for m in MODES_3D if m not in RENDER_MODES),
                        help=f"2D runs: {'|'.join(RENDER_MODES)}; 3D runs: {'|'.join(MODES_3D)} "
                             "(default: the scene's render.mode; mass or color mean surface in 3D)")
    render.add_argument("--size", type=integer(RENDER_SIZE_MIN, RENDER_SIZE_MAX, " pixels"),
                        help=f"image size in pixels, {RENDER_SIZE_MIN} to {RENDER_SIZE_MAX} (default: render.size)")
    render.add_argument("--every", type=integer(1), help="a frame every K >= 1 steps (default: render.every)")
    render.add_argument("--arch", choices=["cpu", "gpu"], help="override sim.arch")

    bench = sub.add_parser("bench", formatter_class=fmt, help="benchmarks (figures for BENCHMARKS.md)")
    bench.add_argument("what", choices=["gradient", "scaling", "tradeoff", "quality"],
                       help="gradient: forward/backward/Tape speed and memory; scaling: the same against "
                            "particles, steps and grid (writes scaling.png); tradeoff: accuracy against time "
                            "over the settings of SCENE; quality: `mls-mpm morph` on a suite of shape pairs "
                            "(iou, mass_error, wall time against targets)")
    bench.add_argument("scene", nargs="?", help="scene file (tradeoff only)")
    bench.add_argument("--out", help="tradeoff: output folder (default: renders/tradeoff_<scene name>/); "
                                     "scaling: folder of scaling.png (default: .); gradient: also write the "
                                     "table to this file (its folder must exist); quality: output folder "
                                     "(default: renders/bench_quality/, with --dim 3 renders/bench_quality_3d/)")
    bench.add_argument("--quick", action="store_true",
                       help="gradient: 40 steps (3D: 10); tradeoff: fewer rows and iterations (under 10 minutes); "
                            "quality: 3 pairs at --quality fast")
    bench.add_argument("--arch", choices=["cpu", "gpu", "cuda", "vulkan"], default="cpu",
                       help="gradient: the Taichi backend measured")
    bench.add_argument("--dim", type=int, choices=[2, 3], default=None,
                       help="gradient: only the cases of this dimension (default: the 2D and the 3D cases); "
                            "quality: the 2D suite of images (default) or the 3D suite of solids and meshes")
    bench.add_argument("--against", metavar="REV", default=None,
                       help="gradient: measure git revision REV (checked out in a temporary worktree, removed "
                            "afterwards) and the working tree side by side, alternating their runs, and print "
                            "both and the speed-ups (old / new); the manual path only, no Tape")
    bench.add_argument("--repeats", type=integer(1), default=None, metavar="K",
                       help="gradient: measured runs of each case (with --against: of each tree, alternating) "
                            "after a warm-up run; the table shows the minimum (default: 1, with --against 3)")
    bench.add_argument("--max-seconds", type=float, default=None,
                       help="tradeoff: wall-time budget of one row; a row over it is stopped and marked (default: "
                            "no limit)")
    bench.add_argument("--workers", type=integer(1), default=None,
                       help="quality: pairs morphed at once, each with cores // N threads (default: 1)")
    bench.add_argument("--quality", choices=["fast", "default", "best"], default=None,
                       help="quality: the morph's --quality (default: default; fast with --quick)")
    bench.add_argument("--pairs", metavar="NAME,...", default=None,
                       help="quality: only these pairs (names in mls_mpm/bench/quality.py, 3D: pairs3d.py; "
                            "default: all)")
    bench.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                       help="quality: passed to every morph, e.g. --set optimize.iterations=10 (repeatable)")
    bench.add_argument("--warm-cache", action="store_true",
                       help="quality: use Taichi's kernel cache as it is (default: each pair compiles in an empty "
                            "cache of its own, as a shape of your own does)")
    return p


def main(argv=None) -> int:
    """Run one command; its exit code. Ctrl-C at any point, imports included, is one line and 130."""
    try:
        return _main(argv)
    except KeyboardInterrupt:
        print("mls-mpm: interrupted", file=sys.stderr)
        return 130


def _main(argv):
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:  # --help (0) or a bad command line (2, one line already printed)
        return e.code if isinstance(e.code, int) else USAGE_ERRORS
    from .errors import SimulationError, UserError

    try:
        return COMMANDS[args.command](args)
    except UserError as e:
        print(f"mls-mpm: error: {e}", file=sys.stderr)
        return USAGE_ERRORS
    except SimulationError as e:
        print(f"mls-mpm: simulation stopped: {e}", file=sys.stderr)
        return 1


def _scene(args):
    from .scene import load_scene

    overrides = list(args.set)
    if getattr(args, "arch", None):
        overrides.append(f"sim.arch={args.arch}")
    return load_scene(args.scene, overrides)


def _interrupted(stop, e):
    """The one line of a render stopped by a signal, and the exit code of that signal."""
    print(f"mls-mpm: interrupted: {e}" if str(e) else "mls-mpm: interrupted while rendering", file=sys.stderr)
    return stop.exit_code()


def cmd_run(args, files=None):
    from pathlib import Path

    from .errors import Interrupted, SimulationError
    from .problem import iou_text
    from .run import run_scene

    scene = args.loaded if files else _scene(args)
    out = Path(args.out) if args.out else Path("renders") / scene.name
    stop = StopFlag()
    restore = stop.install()
    emit = (lambda *_: None) if args.quiet else (lambda msg: print(msg, flush=True))
    try:
        summary = run_scene(scene, out, resume=args.resume, emit=emit, should_stop=stop,
                            render=not args.no_render, files=files)
    except Interrupted as e:
        return _interrupted(stop, e)
    except SimulationError as e:
        ckpt = out / "checkpoint.npz"
        saved = f"; the last good checkpoint is {ckpt}" if ckpt.is_file() else ""
        raise SimulationError(f"{e}{saved}") from None
    finally:
        restore()
    if summary.get("interrupted") or summary.get("render_interrupted"):
        return stop.exit_code()
    if args.quiet:
        print(f"{scene.name}: loss {summary['loss_initial']:.6e} -> {summary['loss_final']:.6e}, "
              f"iou {iou_text(summary['iou'])}")
    return 0


def cmd_morph(args):
    """Choose a scene from the two images, validate it, then run it like `run`, saving it as DIR/scene.toml."""
    import dataclasses
    import tempfile
    from pathlib import Path

    from .morph import choose
    from .scene import SceneError, load_scene

    arch = [f"sim.arch={args.arch}"] if args.arch else []
    choice = choose(args.initial, args.target, args.quality, args.loss, args.seconds, list(args.set) + arch,
                    args.keep_position, dim=args.dim)
    out = Path(args.out) if args.out else Path("renders") / choice.name
    with tempfile.TemporaryDirectory() as tmp:  # validated before anything is written
        path = Path(tmp) / "scene.toml"
        path.write_text(choice.text)
        try:
            scene = load_scene(path)
        except SceneError as e:  # name the scene the user would have got, not the temporary file
            raise SceneError(str(e).replace(str(path.resolve()), f"morph's scene for {out / 'scene.toml'}")) from None
    args.loaded = dataclasses.replace(scene, path=(out / "scene.toml").resolve())
    args.out = str(out)
    if not args.quiet:
        print(choice.line(args.quality), flush=True)
    for note in choice.notes:  # warnings: on stderr, --quiet or not
        print(f"mls-mpm: {note}", file=sys.stderr, flush=True)
    return cmd_run(args, files={"scene.toml": choice.text})


def cmd_check(args):
    from .check import check_scene

    return 0 if check_scene(_scene(args), args) else 1


def cmd_render(args):
    import contextlib
    from pathlib import Path

    from .errors import Interrupted
    from .lock import folder_lock
    from .render_run import render_run

    stop = StopFlag()
    restore = stop.install()
    # a folder that a run (or another render) is writing is refused; a missing one is render_run's to report
    held = folder_lock(args.dir, "render") if Path(args.dir).is_dir() else contextlib.nullcontext()
    try:
        with held:
            render_run(args.dir, mode=args.mode, size=args.size, every=args.every, arch=args.arch,
                       should_stop=stop)
    except Interrupted as e:
        return _interrupted(stop, e)
    finally:
        restore()
    return 0


def cmd_bench(args):
    import math
    from pathlib import Path

    from .bench.output import BenchError

    if args.scene and args.what != "tradeoff":
        raise BenchError(f"bench {args.what}: SCENE {args.scene}: a scene applies to bench tradeoff only; drop it")
    if args.arch != "cpu" and args.what != "gradient":
        raise BenchError(f"bench {args.what}: --arch applies to bench gradient only; drop it")
    if args.dim is not None and args.what not in ("gradient", "quality"):
        raise BenchError(f"bench {args.what}: --dim applies to bench gradient and bench quality only; drop it")
    if args.against is not None and args.what != "gradient":
        raise BenchError(f"bench {args.what}: --against applies to bench gradient only; drop it")
    if args.repeats is not None and args.what != "gradient":
        raise BenchError(f"bench {args.what}: --repeats applies to bench gradient only; drop it")
    if args.max_seconds is not None and (args.what != "tradeoff" or not 0 < args.max_seconds < math.inf):
        raise BenchError(f"bench {args.what}: --max-seconds {args.max_seconds:g}: expected seconds > 0, with bench "
                         "tradeoff only")
    quality_only = [flag for flag, given in (("--workers", args.workers is not None), ("--quality", args.quality),
                                             ("--pairs", args.pairs is not None), ("--set", args.set),
                                             ("--warm-cache", args.warm_cache)) if given]
    if quality_only and args.what != "quality":
        raise BenchError(f"bench {args.what}: {quality_only[0]} applies to bench quality only; drop it")
    if args.what == "quality":
        from .bench import bench_quality

        names = None
        if args.pairs is not None:
            names = [n.strip() for n in args.pairs.split(",") if n.strip()]
            if not names:
                raise BenchError("bench quality: --pairs: expected pair names separated by commas, e.g. "
                                 "--pairs split_two,letter_A")
        bench_quality(quality=args.quality, quick=args.quick, workers=args.workers or 1, out=args.out, names=names,
                      overrides=args.set, warm_cache=args.warm_cache, dim=args.dim or 2)
        return 0
    if args.what == "gradient":
        from .bench import bench_against, bench_gradient

        dims = (2, 3) if args.dim is None else (args.dim,)
        if args.against is not None:
            bench_against(args.against, repeats=args.repeats or 3, quick=args.quick, arch=args.arch, dims=dims,
                          out=args.out)
        else:
            bench_gradient(quick=args.quick, arch=args.arch, out=args.out, dims=dims, repeats=args.repeats or 1)
        return 0
    if args.what == "scaling":
        from .bench import bench_scaling

        bench_scaling(quick=args.quick, plot_path=Path(args.out or ".") / "scaling.png")
        return 0
    from .bench import bench_tradeoff

    if not args.scene:
        raise BenchError("bench tradeoff: expected a SCENE file, e.g. mls-mpm bench tradeoff "
                         "scenes/circle_to_torus.toml")
    bench_tradeoff(args.scene, out=args.out, quick=args.quick, max_seconds=args.max_seconds)
    return 0


COMMANDS = {"run": cmd_run, "morph": cmd_morph, "check": cmd_check, "render": cmd_render, "bench": cmd_bench}

if __name__ == "__main__":
    sys.exit(main())
