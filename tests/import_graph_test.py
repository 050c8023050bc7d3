"""The package's import graph: no module imports another in a circle (function-local
imports included), and inference never reaches the training code."""

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = "c3dpo_jax"


def _modules() -> dict[str, pathlib.Path]:
    out = {}
    for path in (ROOT / PACKAGE).rglob("*.py"):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        out[name.removesuffix(".__init__")] = path
    return out


def _graph(top_level_only: bool) -> dict[str, set[str]]:
    modules, graph = _modules(), {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        nodes = tree.body if top_level_only else ast.walk(tree)
        targets = set()
        for node in nodes:
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(PACKAGE):
                for alias in node.names:  # a submodule, else a name of the module
                    sub = f"{node.module}.{alias.name}"
                    targets.add(sub if sub in modules else node.module)
            elif isinstance(node, ast.Import):
                targets.update(a.name for a in node.names if a.name.startswith(PACKAGE))
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    found, state = [], {}

    def visit(node, stack):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                found.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    return found


def test_no_module_imports_another_in_a_circle():
    assert _cycles(_graph(top_level_only=False)) == []


def _reached(start: str, top_level_only: bool) -> set[str]:
    graph, seen, todo = _graph(top_level_only), set(), [start]
    while todo:
        node = todo.pop()
        if node not in seen:
            seen.add(node)
            todo.extend(graph[node])
    return seen


def test_inference_does_not_import_the_training_code():
    seen = _reached("c3dpo_jax.reconstruct", top_level_only=True)
    assert not seen & {"c3dpo_jax.train", "c3dpo_jax.state"}, sorted(seen)


def test_the_pictures_draw_and_never_load_a_model():
    seen = _reached("c3dpo_jax.visualise", top_level_only=False)
    assert not seen & {"c3dpo_jax.model", "c3dpo_jax.checkpoint", "c3dpo_jax.reconstruct",
                       "c3dpo_jax.inference"}, sorted(seen)
