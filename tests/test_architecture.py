"""The package import graph is the one docs/architecture.md draws: no back edge between packages, no file circle.

Every import counts, module-level or inside a function: a lazy import is still a dependency.
"""

from __future__ import annotations

import ast
import re
import tomllib
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def package_dirs() -> dict[str, Path]:
    """convoy.* package → its folder, from pyproject's package-dir mapping (the one source of the layout)."""
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    dirs = {"convoy": ROOT / "convoy"}
    dirs.update({pkg: ROOT / d for pkg, d in tool["package-dir"].items()})
    return dirs


def modules() -> dict[str, Path]:
    found: dict[str, Path] = {}
    for pkg, folder in package_dirs().items():
        files = folder.glob("*.py") if pkg == "convoy" else folder.rglob("*.py")
        for f in files:
            name = ".".join((pkg, *f.relative_to(folder).with_suffix("").parts)).removesuffix(".__init__")
            found[name] = f
    return found


def module_edges(mods: dict[str, Path]) -> dict[str, set[str]]:
    """module → the Convoy modules it imports (``from pkg import submodule`` is an edge to the submodule)."""
    edges: dict[str, set[str]] = defaultdict(set)
    for name, path in mods.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                subs = [f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in mods]
                targets = subs if len(subs) == len(node.names) else [node.module, *subs]
            edges[name].update(t for t in targets if t in mods and t != name)
    return edges


def node_of(module: str) -> str:
    """The graph's node: a package (convoy.envs) or one of the root modules (convoy.config)."""
    return ".".join(module.split(".")[:2])


def drawn_graph() -> dict[str, set[str]]:
    """The ``import-graph`` block of docs/architecture.md: ``node -> dep, dep`` per line."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    block = re.search(r"```import-graph\n(.*?)```", text, re.S)
    assert block, "docs/architecture.md has no ```import-graph block"
    graph: dict[str, set[str]] = {}
    for line in block.group(1).splitlines():
        if line.strip():
            node, _, deps = line.partition("->")
            graph[node.strip()] = {d.strip() for d in deps.split(",") if d.strip()}
    return graph


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(u: str) -> list[str] | None:
        state[u] = 1
        stack.append(u)
        for v in sorted(edges.get(u, ())):
            if state.get(v) == 1:
                return [*stack[stack.index(v) :], v]
            if v not in state and (cycle := visit(v)):
                return cycle
        stack.pop()
        state[u] = 2
        return None

    for u in sorted(edges):
        if u not in state and (cycle := visit(u)):
            return cycle
    return None


def test_the_package_graph_is_the_one_the_architecture_page_draws() -> None:
    mods = modules()
    drawn = drawn_graph()
    actual: dict[str, set[str]] = defaultdict(set)
    why: dict[tuple[str, str], str] = {}
    for mod, targets in module_edges(mods).items():
        for t in targets:
            a, b = node_of(mod), node_of(t)
            if a != b:
                actual[a].add(b)
                why.setdefault((a, b), f"{mods[mod].relative_to(ROOT)} imports {t}")
    assert set(actual) - set(drawn) == set(), "packages missing from docs/architecture.md's import graph"
    undrawn = sorted(f"{a} -> {b} ({why[a, b]})" for a in actual for b in actual[a] - drawn.get(a, set()))
    assert not undrawn, "imports the architecture does not allow:\n" + "\n".join(undrawn)
    stale = sorted(f"{a} -> {b}" for a in drawn for b in drawn[a] - actual.get(a, set()))
    assert not stale, "edges docs/architecture.md draws but no module imports (redraw it):\n" + "\n".join(stale)
    assert find_cycle(drawn) is None, "the drawn package graph has a circle"


def test_no_module_imports_itself_back() -> None:
    cycle = find_cycle(module_edges(modules()))
    assert cycle is None, "file circle: " + " -> ".join(cycle or [])


def test_the_checker_sees_a_back_edge_and_a_circle() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
    assert node_of("convoy.envs.treadmill.engine") == "convoy.envs"
    assert node_of("convoy.config") == "convoy.config"


def test_protocol_imports_no_env_code() -> None:
    """Transport reaches no env module, not even through another package (the API and actors' wire stay light)."""
    edges = module_edges(modules())
    seen, todo = set(), [m for m in edges if m.startswith("convoy.protocol")]
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(edges.get(m, ()))
    assert not sorted(m for m in seen if m.startswith("convoy.envs")), "protocol reaches env code"


def test_every_package_folder_is_installed() -> None:
    """pyproject lists packages by hand: a new folder with an ``__init__.py`` must be listed or the wheel lacks it."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    on_disk = {m for m, p in modules().items() if p.name == "__init__.py"}
    data_only = {"convoy.api.static"}  # the dashboard's files: a package of data, no code
    assert on_disk | data_only == listed, f"missing: {sorted(on_disk - listed)}; stale: {sorted(listed - on_disk)}"


# One source for each truth: where two modules need the same list, one defines it and the other imports it.

SKIP_DIRS = {"tests", ".venv", "runs", "convoy.egg-info"}


def product_sources() -> list[Path]:
    """Every Python file of the product (the packages, benchmarks, experiments): the tree less tests and tooling."""
    folders = lambda p: p.relative_to(ROOT).parts[:-1]  # noqa: E731
    return sorted(p for p in ROOT.rglob("*.py") if not any(d in SKIP_DIRS or d[0] == "." for d in folders(p)))


def test_one_place_picks_the_matplotlib_backend() -> None:
    """``matplotlib.use(`` once, in convoy.output.pyplot, which every plotting module calls for pyplot."""
    found = sorted(str(p.relative_to(ROOT)) for p in product_sources() if "matplotlib.use(" in p.read_text())
    assert found == ["convoy/output.py"], found


def test_pyplot_renders_headless(tmp_path: Path) -> None:
    from convoy.output import pyplot, save_figure

    plt = pyplot()
    assert plt.get_backend().lower() == "agg"
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    assert save_figure(fig, tmp_path / "a" / "fig.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_job_flags_and_sweep_grid_fields_are_one_list() -> None:
    from convoy.api.models import GRID_FIELDS
    from convoy.cli.train import JOB_FLAGS
    from convoy.config import JOB_FIELDS, JobConfig

    assert JOB_FLAGS is GRID_FIELDS is JOB_FIELDS
    assert set(JOB_FIELDS) <= set(JobConfig.model_fields)


def test_the_cli_and_the_api_share_the_final_states() -> None:
    from convoy.api.lifecycle import FINAL_STATES, JobState
    from convoy.cli import jobs

    assert jobs.FINAL_STATES is FINAL_STATES
    assert tuple(JobState) == jobs.STATES
