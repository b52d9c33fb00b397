"""The package's import graph has no cycles, counting imports inside functions too."""

import ast
import subprocess
import sys
from pathlib import Path

import lbo

SRC = Path(lbo.__file__).parent


def import_graph() -> dict[str, set[str]]:
    """lbo module -> the lbo modules it imports anywhere in its text."""
    files = {}
    for f in SRC.rglob("*.py"):
        name = ".".join(("lbo", *f.relative_to(SRC).with_suffix("").parts))
        files[name.removesuffix(".__init__")] = f
    graph: dict[str, set[str]] = {m: set() for m in files}
    for mod, f in files.items():
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("lbo"):
                for alias in node.names:
                    sub = f"{node.module}.{alias.name}"  # from lbo.pkg import submodule
                    graph[mod].add(sub if sub in files else node.module)
            elif isinstance(node, ast.Import):
                graph[mod].update(a.name for a in node.names if a.name in files)
        graph[mod] &= set(files) - {mod}
    return graph


def cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle, as a path of modules, or None."""
    state: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(node: str, path: list[str]) -> list[str] | None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt] if nxt in path else [node, nxt]
            if nxt not in state and (found := visit(nxt, [*path, nxt])):
                return found
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (found := visit(start, [start])):
            return found
    return None


def test_no_import_cycles():
    graph = import_graph()
    assert "lbo.engines" in graph["lbo.export"] and "lbo.engines" in graph["lbo.observer"]
    assert cycle(graph) is None, " -> ".join(cycle(graph))


def test_the_cycle_finder_finds_a_cycle():
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b"}, "b": set()}) is None


def test_export_and_observer_import_in_a_fresh_interpreter():
    res = subprocess.run([sys.executable, "-c", "import lbo.export, lbo.observer"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def test_a_missing_conf_folder_is_one_line(tmp_path):
    res = subprocess.run([sys.executable, "-m", "lbo.evaluate"], capture_output=True,
                         text=True, env={"LBO_ROOT": str(tmp_path), "PATH": "/usr/bin:/bin"})
    assert res.returncode == 2
    assert res.stderr.strip() == (f"error: lbo's configs are neither in {tmp_path / 'conf'} "
                                  "nor in the installed package: reinstall lbo (pip install "
                                  "<repo>), or set LBO_ROOT=<repo>")
