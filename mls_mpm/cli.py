"""Command line: mls-mpm run | check | render | bench. `main(argv) -> int`; Taichi starts only inside a command."""
import argparse
import signal
import sys
from pathlib import Path

USAGE_ERRORS = 2


class StopFlag:
    """Set by SIGINT/SIGTERM; the optimizer checkpoints and returns when it sees it."""

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
            print(f"\nmls-mpm: got signal {signum}; saving a checkpoint after the current step...", file=sys.stderr,
                  flush=True)

        for sig in previous:
            signal.signal(sig, handler)
        return lambda: [signal.signal(sig, h) for sig, h in previous.items()]


def build_parser():
    fmt = argparse.ArgumentDefaultsHelpFormatter
    p = argparse.ArgumentParser(prog="mls-mpm", formatter_class=fmt,
                                description="Differentiable MLS-MPM shape morphing (thesis: M. Xu, 2020).")
    sub = p.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", formatter_class=fmt, help="optimize a scene and render its animation")
    run.add_argument("scene", help="scene file (TOML), see scenes/README.md")
    run.add_argument("--out", help="output folder (default: renders/<scene name>/)")
    run.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                     help="override a scene key, e.g. --set sim.n_grid=128 (repeatable)")
    run.add_argument("--arch", choices=["cpu", "gpu"], help="override sim.arch")
    run.add_argument("--resume", action="store_true", help="continue an interrupted run from its checkpoint")
    run.add_argument("--no-render", action="store_true", help="skip frames, gif and sheet")
    run.add_argument("--quiet", action="store_true", help="print only the final line")

    check = sub.add_parser("check", formatter_class=fmt,
                           help="compare the manual gradient with ti.ad.Tape and finite differences")
    check.add_argument("scene")
    check.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    check.add_argument("--steps", type=int, default=12, help="steps of the reduced scene")
    check.add_argument("--particles", type=int, default=300, help="particles kept (an even subsample)")
    check.add_argument("--tol-tape", type=float, default=1e-6, help="largest relative error against Tape")
    check.add_argument("--tol-fd", type=float, default=1e-5, help="largest relative error against FD")

    render = sub.add_parser("render", formatter_class=fmt, help="re-render a finished run from its result.npz")
    render.add_argument("dir", help="output folder of a finished run")
    render.add_argument("--mode", choices=["mass", "color", "particles"], help="default: the scene's render.mode")
    render.add_argument("--size", type=int, help="image size in pixels (default: render.size)")
    render.add_argument("--every", type=int, help="a frame every K steps (default: render.every)")
    render.add_argument("--arch", choices=["cpu", "gpu"], help="override sim.arch")

    bench = sub.add_parser("bench", formatter_class=fmt, help="benchmarks (figures for BENCHMARKS.md)")
    bench.add_argument("what", choices=["gradient", "scaling", "tradeoff"],
                       help="gradient: forward/backward/Tape speed and memory; scaling: the same against "
                            "particles, steps and grid (writes scaling.png); tradeoff: accuracy against time "
                            "over the settings of SCENE")
    bench.add_argument("scene", nargs="?", help="scene file (tradeoff only)")
    bench.add_argument("--out", help="tradeoff: output folder (default: renders/tradeoff_<scene name>/); "
                                     "scaling: folder of scaling.png (default: .); gradient: also write the "
                                     "table to this file")
    bench.add_argument("--quick", action="store_true",
                       help="gradient: 40 steps; tradeoff: fewer rows and iterations (under 10 minutes)")
    bench.add_argument("--arch", choices=["cpu", "gpu", "cuda", "vulkan"], default="cpu",
                       help="gradient: the Taichi backend measured")
    bench.add_argument("--max-seconds", type=float, default=None,
                       help="tradeoff: wall-time budget of one row; a row over it is stopped and marked (default: "
                            "no limit)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from .errors import SimulationError, UserError

    try:
        return COMMANDS[args.command](args)
    except UserError as e:
        print(f"mls-mpm: error: {e}", file=sys.stderr)
        return USAGE_ERRORS
    except SimulationError as e:
        print(f"mls-mpm: simulation stopped: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("mls-mpm: interrupted", file=sys.stderr)
        return 130


def _scene(args):
    from .scene import load_scene

    overrides = list(args.set)
    if getattr(args, "arch", None):
        overrides.append(f"sim.arch={args.arch}")
    return load_scene(args.scene, overrides)


def cmd_run(args):
    from .run import run_scene

    scene = _scene(args)
    out = Path(args.out) if args.out else Path("renders") / scene.name
    stop = StopFlag()
    restore = stop.install()
    emit = (lambda *_: None) if args.quiet else (lambda msg: print(msg, flush=True))
    from .simulator import SimulationError

    try:
        summary = run_scene(scene, out, resume=args.resume, emit=emit, should_stop=stop,
                            render=not args.no_render)
    except SimulationError as e:
        ckpt = out / "checkpoint.npz"
        saved = f"; the last good checkpoint is {ckpt}" if ckpt.is_file() else ""
        raise SimulationError(f"{e}{saved}") from None
    finally:
        restore()
    if summary.get("interrupted"):
        return 130 if stop.signal == signal.SIGINT else 143
    if args.quiet:
        print(f"{scene.name}: loss {summary['loss_initial']:.6e} -> {summary['loss_final']:.6e}, "
              f"iou {summary['iou']:.3f}")
    return 0


def cmd_check(args):
    from .check import check_scene

    return 0 if check_scene(_scene(args), args) else 1


def cmd_render(args):
    from .render_run import render_run

    render_run(args.dir, mode=args.mode, size=args.size, every=args.every, arch=args.arch)
    return 0


def cmd_bench(args):
    from .scene import SceneError

    if args.arch != "cpu" and args.what != "gradient":
        raise SceneError(f"bench {args.what}: --arch applies to bench gradient only; drop it")
    if args.max_seconds is not None and (args.what != "tradeoff" or not args.max_seconds > 0):
        raise SceneError(f"bench {args.what}: --max-seconds {args.max_seconds:g}: expected seconds > 0, with bench "
                         "tradeoff only")
    if args.what == "gradient":
        from .bench import bench_gradient

        bench_gradient(quick=args.quick, arch=args.arch, out=args.out)
        return 0
    if args.what == "scaling":
        from .bench import bench_scaling

        bench_scaling(quick=args.quick, plot_path=Path(args.out or ".") / "scaling.png")
        return 0
    from .tradeoff import bench_tradeoff

    if not args.scene:
        raise SceneError("bench tradeoff: expected a SCENE file, e.g. mls-mpm bench tradeoff scenes/circle_to_torus.toml")
    bench_tradeoff(args.scene, out=args.out, quick=args.quick, max_seconds=args.max_seconds)
    return 0


COMMANDS = {"run": cmd_run, "check": cmd_check, "render": cmd_render, "bench": cmd_bench}

if __name__ == "__main__":
    sys.exit(main())
