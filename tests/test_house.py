"""The shape of the package: what a newcomer can rely on when finding their way around.

No import circle between jaxmap's modules, no module over 500 lines and no function over 60 lines outside
the synthetic scenes (`jaxmap/synth/`, long tables of geometry), no private name imported from another
module, one frame loop (every run goes through `jaxmap.frame_loop.run_frames`), and the maps below the runs."""
import ast
import pathlib

import pytest

PKG = pathlib.Path(__file__).resolve().parents[1] / "jaxmap"
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 60


def _modules():
    for path in sorted(PKG.rglob("*.py")):
        name = ".".join(path.relative_to(PKG.parent).with_suffix("").parts)
        yield name.removesuffix(".__init__"), path


def _exempt(name: str) -> bool:
    return name.startswith("jaxmap.synth")


def _imports(name: str, tree: ast.AST, known: set[str]):
    """(imported module, [names], line) of every jaxmap import in `tree`, relative ones resolved."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("jaxmap"):
                    yield a.name, [], node.lineno
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("jaxmap"):
            names = [a.name for a in node.names]
            # `from jaxmap.pkg import module` imports the module
            subs = [f"{node.module}.{n}" for n in names if f"{node.module}.{n}" in known]
            yield node.module, [n for n in names if f"{node.module}.{n}" not in known], node.lineno
            for s in subs:
                yield s, [], node.lineno


def _graph():
    mods = dict(_modules())
    known = set(mods)
    edges, private = {}, []
    for name, path in mods.items():
        tree = ast.parse(path.read_text())
        deps = set()
        for target, names, line in _imports(name, tree, known):
            if target in known and target != name:
                deps.add(target)
            private += [f"{name}:{line} imports {target}.{n}" for n in names if n.startswith("_")]
        edges[name] = deps
    return edges, private


def test_no_import_circle():
    edges, _ = _graph()
    # a package's __init__ that only hands names on is not a room: drop edges into packages
    packages = {n for n in edges if (PKG.parent / n.replace(".", "/") / "__init__.py").is_file()}
    graph = {n: {d for d in ds if d not in packages} for n, ds in edges.items() if n not in packages}
    state, circles = {}, []

    def visit(n, stack):
        state[n] = 1
        stack.append(n)
        for d in sorted(graph.get(n, ())):
            if state.get(d) == 1:
                circles.append(stack[stack.index(d):] + [d])
            elif d not in state:
                visit(d, stack)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [])
    assert not circles, "import circles: " + "; ".join(" -> ".join(c) for c in circles)


def test_no_private_name_crosses_a_module():
    _, private = _graph()
    assert not private, "\n".join(private)


def test_modules_and_functions_stay_small():
    big, long = [], []
    for name, path in _modules():
        if _exempt(name):
            continue
        text = path.read_text()
        n = len(text.splitlines())
        if n > MAX_MODULE_LINES:
            big.append(f"{name}: {n} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    long.append(f"{name}.{node.name} (line {node.lineno}): {length} lines")
    assert not big and not long, "\n".join(big + long)


@pytest.mark.parametrize("call", ['unit="frame"', "attach_viewer(", "interrupt_requests("])
def test_one_frame_loop(call):
    """The frame-by-frame progress bar, the viewer hooks and the Ctrl-C handling of a run are made in one
    place: every pass over a sequence's frames (mapping, odometry, baselines, evaluation) is a step of
    `jaxmap.frame_loop.run_frames`."""
    users = [name for name, path in _modules() if call in path.read_text()
             and name not in ("jaxmap.frame_loop", "jaxmap.viewer", "jaxmap.rundir")]
    assert not users, f"{call} outside jaxmap.frame_loop: {users}"


RUN_LAYER = ("jaxmap.frame_loop", "jaxmap.viewer", "jaxmap.finish", "jaxmap.runs")


def test_maps_and_slam_geometry_stay_below_the_run_layer():
    """The maps (`jaxmap.n3`, `jaxmap.imt`) and the SLAM geometry (`jaxmap.slam`: odometry, loops, pose
    graph, tracking, levelling) are libraries a notebook or a script drives frame by frame: they import
    nothing of the runs built on them (the frame loop, the viewer, the finisher, `jaxmap.runs`, where
    `jaxmap slam` and `jaxmap localize` live)."""
    edges, _ = _graph()
    up = [f"{m} imports {d}" for m, deps in edges.items() if m.startswith(("jaxmap.n3", "jaxmap.imt", "jaxmap.slam"))
          for d in deps if d.startswith(RUN_LAYER)]
    assert not up, up


def test_no_package_attribute_shadows_its_submodule():
    """After `import jaxmap.pkg`, `jaxmap.pkg.name` is the submodule `name` wherever such a submodule
    exists: a function exported under a module's name (`jaxmap.imt.remap` the function, not the module)
    makes `import jaxmap.pkg.name as m` and `jaxmap.pkg.name.x` mean different things by import order."""
    import importlib
    import pkgutil
    import sys

    shadowed = []
    for init in sorted(PKG.rglob("__init__.py")):
        name = ".".join(init.parent.relative_to(PKG.parent).parts)
        pkg = importlib.import_module(name)
        for sub in pkgutil.iter_modules(pkg.__path__):
            full = f"{name}.{sub.name}"
            if hasattr(pkg, sub.name) and getattr(pkg, sub.name) is not sys.modules.get(full):
                shadowed.append(f"{full}: {getattr(pkg, sub.name)!r}")
    assert not shadowed, "package attributes that shadow a submodule:\n" + "\n".join(shadowed)
