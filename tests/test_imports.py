"""The package's import graph has no cycles, and no library imports a command, counting imports
inside functions too."""

import ast
import re
import subprocess
import sys
from pathlib import Path
from typing import cast

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
    assert "lbo.serve.engines" in graph["lbo.export"]
    assert "lbo.serve.engines" in graph["lbo.serve.runners"]
    assert cycle(graph) is None, " -> ".join(cycle(graph))


def commands() -> set[str]:
    """The modules behind ``python -m lbo.<command>``: those that build their entry point with
    :func:`lbo.core.cli.entry`."""
    out = set()
    for f in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module == "lbo.core.cli" and \
                    any(a.name == "entry" for a in node.names):
                name = ".".join(("lbo", *f.relative_to(SRC).with_suffix("").parts))
                out.add(name.removesuffix(".__init__"))
    return out


def test_no_library_imports_a_command():
    graph, cmds = import_graph(), commands()
    assert {"lbo.train", "lbo.evaluate", "lbo.observe", "lbo.simulate", "lbo.tune",
            "lbo.reproduce", "lbo.export", "lbo.datagen"} <= cmds
    wrong = sorted(f"{mod} imports {cmd}" for mod in set(graph) - cmds
                   for cmd in graph[mod] & cmds)
    assert not wrong, "; ".join(wrong)


from lbo import LAYERS  # noqa: E402  (the layers, bottom up)


def layer(module: str) -> int:
    """The rank of ``module``'s layer (``lbo.<layer>`` or a module in it); len(LAYERS) for a
    command or the package itself."""
    parts = module.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else len(LAYERS)


def test_every_module_sits_in_a_layer_or_is_a_command():
    graph, cmds = import_graph(), commands()
    # lbo.__main__: the console script, on top with the commands it dispatches to
    stray = sorted(m for m in graph if layer(m) == len(LAYERS)
                   and m not in cmds | {"lbo", "lbo.__main__"})
    assert not stray, f"neither in a layer {LAYERS} nor a command: {stray}"
    assert {p.name for p in SRC.iterdir() if p.is_dir() and p.name != "__pycache__"} == \
        set(LAYERS)


def test_the_console_script_runs_every_command():
    from lbo.__main__ import COMMANDS

    assert {f"lbo.{name}" for name in COMMANDS} == commands()


def upward(graph: dict[str, set[str]]) -> list[str]:
    """Every import of a module from a layer above its own."""
    return sorted(f"{mod} imports {dep}" for mod in graph for dep in graph[mod]
                  if layer(dep) > layer(mod))


def test_no_module_imports_from_a_layer_above_its_own():
    up = upward(import_graph())
    assert not up, "; ".join(up)


def test_the_layer_rule_catches_an_import_upward():
    assert upward({"lbo.sim.vehicle": {"lbo.core.errors", "lbo.sim.noise"},
                   "lbo.train": {"lbo.learn.draws"}}) == []
    assert upward({"lbo.core.atomic": {"lbo.sim.schema"},
                   "lbo.serve.observer": {"lbo.learn", "lbo.train"}}) == [
        "lbo.core.atomic imports lbo.sim.schema", "lbo.serve.observer imports lbo.learn",
        "lbo.serve.observer imports lbo.train"]


def test_the_cycle_finder_finds_a_cycle():
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b"}, "b": set()}) is None


def test_export_and_observer_import_in_a_fresh_interpreter():
    res = subprocess.run([sys.executable, "-c", "import lbo.export, lbo.serve.observer"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def test_a_missing_conf_folder_is_one_line(tmp_path):
    res = subprocess.run([sys.executable, "-m", "lbo.evaluate"], capture_output=True,
                         text=True, env={"LBO_ROOT": str(tmp_path), "PATH": "/usr/bin:/bin"})
    assert res.returncode == 2
    assert res.stderr.strip() == (f"error: lbo's configs are neither in {tmp_path / 'conf'} "
                                  "nor in the installed package: reinstall lbo (pip install "
                                  "<repo>), or set LBO_ROOT=<repo>")


def test_the_documented_layout_names_every_layer_in_order_and_every_command():
    design = (SRC.parents[1] / "docs" / "design.md").read_text()
    section = design.split("## Layout\n", 1)[1].split("\n## ", 1)[0]
    rows = [line.split("|")[1].strip().strip("`/") for line in section.splitlines()
            if line.startswith("| `")]
    assert tuple(rows) == LAYERS
    listed = set(re.findall(r"`(\w+)`", section.split("On top sit the commands", 1)[1]))
    assert {c.removeprefix("lbo.").removesuffix(".__main__") for c in commands()} == \
        listed - {"python"}


MODULE_LINES = 450
"""The most lines a module of src/lbo holds: a module over it holds more than one idea."""


def test_no_module_is_over_the_line_limit():
    long = {str(f.relative_to(SRC)): n for f in SRC.rglob("*.py")
            if (n := len(f.read_text().splitlines())) > MODULE_LINES}
    assert not long, f"modules over {MODULE_LINES} lines: {long}"


POSITIONAL_FIELDS = 3
"""The most fields a dataclass of src/lbo takes by position: the settings after them are
keyword-only (``kw_only=True``, or after a ``_: KW_ONLY`` marker)."""


def positional_fields(cls: ast.ClassDef) -> int | None:
    """How many fields of a dataclass's definition are taken by position (None: not a
    dataclass)."""
    decorators = [ast.unparse(d) for d in cls.decorator_list]
    if not any("dataclass" in d for d in decorators):
        return None
    if any("kw_only=True" in d for d in decorators):
        return 0
    fields = 0
    for node in cls.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            if ast.unparse(node.annotation) in ("KW_ONLY", "dataclasses.KW_ONLY"):
                return fields
            if "ClassVar" not in ast.unparse(node.annotation):
                fields += 1
    return fields


def test_no_dataclass_takes_more_than_three_fields_by_position():
    wide = {f"{f.relative_to(SRC)}:{node.name}": n for f in SRC.rglob("*.py")
            for node in ast.walk(ast.parse(f.read_text())) if isinstance(node, ast.ClassDef)
            and (n := positional_fields(node)) is not None and n > POSITIONAL_FIELDS}
    assert not wide, f"dataclasses with more than {POSITIONAL_FIELDS} positional fields: {wide}"


def test_the_positional_field_count_reads_both_forms_of_keyword_only():
    def count(text: str) -> int | None:
        return positional_fields(cast(ast.ClassDef, ast.parse(text).body[0]))

    assert count("@dataclass(frozen=True)\nclass A:\n a: int\n b: int\n c: int\n d: int") == 4
    assert count("@dataclass(frozen=True, kw_only=True)\nclass A:\n a: int\n b: int") == 0
    assert count("@dataclass\nclass A:\n a: int\n _: KW_ONLY\n b: int\n c: int\n d: int") == 1
    assert count("class A:\n a: int") is None
