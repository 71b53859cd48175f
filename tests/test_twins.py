"""Every forward function of the step has its reverse twin, named `<forward name>_reverse`, in the adjoint module
of the same name, or is listed in adjoint.NO_TWIN with the reason; every twin is exercised by
tests/test_adjoint_kernels.py. Reads source only: no Taichi kernel is compiled."""
import ast
import importlib
import re
from pathlib import Path

import pytest

import adjoint

ROOT = Path(__file__).resolve().parents[1]
MODULES = ("transfer", "grid", "material", "losses", "step", "persistent", "active")


def functions(path):
    """Public top-level functions (kernels, funcs, Python helpers) defined in a module's source."""
    tree = ast.parse(Path(path).read_text())
    return {node.name for node in tree.body if isinstance(node, ast.FunctionDef) and not node.name.startswith("_")}


@pytest.mark.parametrize("module", MODULES)
def test_every_forward_function_has_its_twin_or_a_reason(module):
    forward = functions(ROOT / "mls_mpm" / f"{module}.py")
    twins = adjoint.TWINS.get(module, {})
    exempt = adjoint.NO_TWIN.get(module, {})
    assert not set(twins) & set(exempt), f"{module}: listed both with and without a twin"
    assert forward == set(twins) | set(exempt), (
        f"mls_mpm/{module}.py: not in adjoint.TWINS or NO_TWIN: {sorted(forward - set(twins) - set(exempt))}; "
        f"listed but not defined: {sorted((set(twins) | set(exempt)) - forward)}")
    reverse = importlib.import_module(f"adjoint.{module}") if twins else None
    for name, equations in twins.items():
        assert hasattr(reverse, f"{name}_reverse"), f"adjoint/{module}.py has no {name}_reverse"
        assert equations, name
    for name, reason in exempt.items():
        assert len(reason) > 10, name


def test_every_reverse_function_is_a_twin_or_a_helper():
    """adjoint/<module>.py defines the twins of its forward module; any other public name ends in neither
    `_reverse` (a twin without a forward) nor hides one: helpers are named apart (scatter_adj_node)."""
    for module in MODULES:
        forward = functions(ROOT / "mls_mpm" / f"{module}.py")
        if module not in adjoint.TWINS:  # no twin at all (active: integer bookkeeping): no adjoint module
            assert not (ROOT / "adjoint" / f"{module}.py").exists(), module
            continue
        for name in functions(ROOT / "adjoint" / f"{module}.py"):
            if name.endswith("_reverse"):
                assert name[: -len("_reverse")] in forward, f"adjoint/{module}.py: {name} has no forward twin"
                assert name[: -len("_reverse")] in adjoint.TWINS[module], f"{name}: missing from adjoint.TWINS"


def test_every_twin_is_exercised_by_the_kernel_tests():
    """Each twin is called (or named in the docstring of the test that drives it) in test_adjoint_kernels.py."""
    source = (ROOT / "tests" / "test_adjoint_kernels.py").read_text()
    missing = [f"{name}_reverse" for twins in adjoint.TWINS.values() for name in twins
               if not re.search(rf"\b{name}_reverse\b", source)]
    assert not missing, f"tests/test_adjoint_kernels.py never exercises {missing}"


def test_adjoint_variables_have_one_prefix():
    """Adjoint variables are adj_<forward variable>: no g_v, g_C, g_x, g_m, g_p, k_a; and `g` is a loss grid only
    (adjoint/losses.py, as in mls_mpm/losses.py), never a gradient beside gravity's g."""
    for path in sorted((ROOT / "adjoint").glob("*.py")):
        names = {node.id for node in ast.walk(ast.parse(path.read_text())) if isinstance(node, ast.Name)}
        old = sorted(n for n in names if re.fullmatch(r"g_\w+|k_[ab]", n) or (n == "g" and path.name != "losses.py"))
        assert not old, f"{path.name}: adjoint variables not named adj_<name>: {old}"
