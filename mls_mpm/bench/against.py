"""`mls-mpm bench gradient --against REV`: a git revision and the working tree measured side by side in one run,
so that a speed-up is a ratio of figures from one machine at one moment.

REV is checked out in a temporary git worktree, removed afterwards (also after an error, Ctrl-C or SIGTERM). For
each case (the working tree's cases and steps) the children of child.py run alternately, REV then the working
tree, one warm-up each (it fills Taichi's offline cache) and then `repeats` measured runs each. A child imports
its own tree's mls_mpm and adjoint (PYTHONPATH and working folder), with this interpreter, and runs that tree's
own `measure(case, path, steps)`. Every figure is the minimum over the repeats: the run the rest of the machine
disturbed least.
"""
import contextlib
import datetime
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from ..config import COMPILE_VARIABLE, compile_mode
from .child import CASES, TINY_PARTICLES, TINY_STEPS, backend_here, case_label, case_steps, run_child
from .gradient import MEMORY_CPU, measured_on
from .output import BenchError, writable_file

ROOT = Path(__file__).resolve().parents[2]  # the source tree this package is imported from: the working tree
SIGTERM_EXIT = 143  # 128 + SIGTERM, as the CLI's


def bench_against(rev, repeats=3, quick=False, arch="cpu", dims=(2, 3), out=None, emit=print, progress=None,
                  cases=None):
    """Print the table of REV against the working tree (and return its rows); out: also write it there.

    progress(text): a line before every child (default: to stderr). cases: {name: case dict} instead of CASES (for
    tests). A REV that is not a commit of the repository, or has no child.py `measure`, and an `out` that cannot be
    written are refused (BenchError) before anything is measured."""
    commit, old = resolve(rev)
    if out:
        writable_file(out)
    backend = "cpu" if arch == "cpu" else backend_here(arch)
    new = _git("rev-parse", "--short", "HEAD").stdout.strip()
    dirty = " + uncommitted changes" if _git("status", "--porcelain").stdout.strip() else ""
    progress = progress or (lambda text: print(text, file=sys.stderr, flush=True))
    rows = []
    with sigterm_unwinds(), worktree(commit) as tree:
        trees = {"old": tree, "new": ROOT}
        for case in (cases or CASES).values():
            if case.get("dim", 2) not in dims:
                continue
            case = dict(case, arch=arch)
            steps = case_steps(case, quick)
            what = f"bench gradient --against {rev}: {case_label(case, steps)}"
            runs = alternate(case, steps, trees, repeats, backend, lambda text: progress(f"{what}: {text}"))
            base = None  # memory: the same path at the tiny size (a case of that size is its own), on the CPU only
            if backend == "cpu":
                own = (case["particles"], steps) == (TINY_PARTICLES, TINY_STEPS)
                base = runs if own else alternate(case, steps, trees, 1, backend,
                                                  lambda text: progress(f"{what}, tiny: {text}"), tiny=True)
            rows.append(dict(case=case_label(case, steps), runs=runs, base=base))
    when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = _table(rows, repeats, backend, f"old: {rev} = {old}; new: the working tree at {new}{dirty}; {when}"
                   + _compile_note(commit, rev, backend))
    for line in lines:
        emit(line)
    if out:
        from ..checkpoint import atomic_write

        atomic_write(out, lambda fh: fh.write(("\n".join(lines) + "\n").encode()))
    return rows


def _compile_note(commit, rev, backend):
    """What the header says when the two trees cannot compile alike: REV from before MLS_MPM_COMPILE (14b3bd8)
    always compiles optimized, while this tree compiles as compile_mode() says (the children are told it)."""
    config = _git("show", f"{commit}:mls_mpm/config.py").stdout
    if backend != "cpu" or compile_mode() == "optimized" or COMPILE_VARIABLE in config:
        return ""
    return (f"; {rev} predates {COMPILE_VARIABLE} and compiles optimized, the working tree {compile_mode()}: "
            f"{COMPILE_VARIABLE}=optimized compares like with like")


def _table(rows, repeats, backend, revisions):
    """The header lines and the markdown table: per case both trees' least ms/step, the speed-ups, bwd / fwd and
    the memory of each (CPU only)."""
    memory = MEMORY_CPU if backend == "cpu" else "not measured (the fields live in device memory)"
    lines = [f"{measured_on(backend)}; {revisions}.",
             f"Each figure: the minimum over {repeats} runs of each, alternating old and new after a warm-up run of "
             f"each; speed-up: old ms / new ms (> 1: new is faster). Memory (manual path): {memory}.", "",
             "| case | old fwd ms/step | new fwd ms/step | fwd speed-up | old bwd ms/step | new bwd ms/step | "
             "bwd speed-up | old bwd / fwd | new bwd / fwd | old MiB | new MiB |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        fwd, bwd = _least(row["runs"], "forward_ms"), _least(row["runs"], "backward_ms")
        memory = "- | -"
        if row["base"]:
            peak, base = _least(row["runs"], "peak_mib"), _least(row["base"], "peak_mib")
            memory = f"{peak['old'] - base['old']:.0f} | {peak['new'] - base['new']:.0f}"
        lines.append(f"| {row['case']} | {fwd['old']:.3f} | {fwd['new']:.3f} | {fwd['old'] / fwd['new']:.2f} | "
                     f"{bwd['old']:.3f} | {bwd['new']:.3f} | {bwd['old'] / bwd['new']:.2f} | "
                     f"{bwd['old'] / fwd['old']:.2f} | {bwd['new'] / fwd['new']:.2f} | {memory} |")
    return lines


def alternate(case, steps, trees, repeats, backend, progress, tiny=False):
    """The manual path's children of one case: a warm-up run in each tree, then `repeats` measured runs in each,
    alternating between the trees; {tree's name: [results]}. A child that imported another tree's mls_mpm, or ran
    on another backend, is an error."""
    runs = {name: [] for name in trees}
    for i in range(repeats + 1):
        for name, tree in trees.items():
            progress(f"{name} ({tree}), " + (f"repeat {i}/{repeats}" if i else "warm-up"))
            got = run_child(case, "manual", steps, tiny=tiny, tree=tree)
            if (tree / got["mls_mpm"]).resolve() != (tree / "mls_mpm" / "__init__.py").resolve():
                raise RuntimeError(f"the child meant for {tree} imported {got['mls_mpm']}")
            if got["backend"] != backend:
                raise RuntimeError(f"a benchmark child ran on {got['backend']}, not {backend}")
            if i:
                runs[name].append(got)
    return runs


def _least(runs, key):
    """{tree's name: the least `key` over its runs}."""
    return {name: min(r[key] for r in results) for name, results in runs.items()}


def resolve(rev):
    """(full hash, short hash) of rev in the repository of ROOT; BenchError where ROOT is not a git checkout, rev
    names no commit there, or that commit has no mls_mpm/bench/child.py `measure` to run."""
    said = f"bench gradient --against {rev}"
    top = _git("rev-parse", "--show-toplevel")
    if top.returncode or Path(top.stdout.strip()).resolve() != ROOT:
        raise BenchError(f"{said}: mls_mpm is imported from {ROOT}, which is not a git checkout; run it in a clone")
    found = None if rev.startswith("-") else _git("rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}")
    if found is None or found.returncode:
        raise BenchError(f"{said}: not a revision of the repository at {ROOT}; expected a commit, branch or tag, "
                         "e.g. HEAD~3")
    commit = found.stdout.strip()
    child = _git("show", f"{commit}:mls_mpm/bench/child.py")
    if child.returncode or "\ndef measure(" not in child.stdout:
        raise BenchError(f"{said}: revision {commit[:10]} has no mls_mpm/bench/child.py measure(case, path, steps) "
                         "to run; pick a later one")
    return commit, _git("rev-parse", "--short", commit).stdout.strip()


@contextlib.contextmanager
def worktree(commit):
    """A detached git worktree of commit in a temporary folder; removed, and git's record of it pruned, on the way
    out whichever way that is."""
    folder = Path(tempfile.mkdtemp(prefix="mls-mpm-against-"))
    tree = folder / "tree"
    try:
        res = _git("worktree", "add", "--detach", str(tree), commit)
        if res.returncode:
            reason = (res.stderr.strip().splitlines() or ["?"])[-1]
            raise BenchError(f"bench gradient --against: cannot check out {commit[:10]} in {tree}: {reason}")
        yield tree
    finally:
        _git("worktree", "remove", "--force", str(tree))
        shutil.rmtree(folder, ignore_errors=True)
        _git("worktree", "prune")


@contextlib.contextmanager
def sigterm_unwinds():
    """Inside the block SIGTERM exits through the `finally` clauses (exit 143) instead of killing at once, so that
    the temporary worktree is removed; the previous handler is put back afterwards. Signals reach the main thread
    only: elsewhere this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, _frame):
        print(f"\nmls-mpm: got signal {signum} (SIGTERM); removing the temporary worktree", file=sys.stderr)
        raise SystemExit(SIGTERM_EXIT)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _git(*args):
    """git run in ROOT: the completed process (returncode, stdout, stderr), or BenchError without git."""
    try:
        return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True)
    except OSError as e:
        raise BenchError(f"bench gradient --against: cannot run git ({e.strerror or e})") from None
