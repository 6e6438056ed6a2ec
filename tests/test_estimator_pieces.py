"""The pieces of an estimator as types, and the registry the rest of the library reads (pipps.propagation).

* every built-in piece is an instance of its kind's :class:`typing.Protocol`, with the protocol's
  methods under the protocol's parameter names, and every registered estimator is made of them;
* pipps/propagation has no import cycle, function-local and ``TYPE_CHECKING`` imports included
  (read from the source with ``ast``); a cycle planted in a copy is found;
* nothing outside the composition asks an estimator or a piece for its type: no ``isinstance``
  against a class of pipps/propagation anywhere else in the package;
* the registry is the one source of names, labels and colours: docs/estimators.md's table is
  :func:`~pipps.propagation.estimators.estimator_table`, and the studies' labels and colours and the
  CLI's help are the registry's;
* a name with settings (``"tp:k_lr=previous"``) is the estimator those settings give.
"""

from __future__ import annotations

import ast
import inspect
import typing
from pathlib import Path

import pytest

from pipps.propagation import pieces
from pipps.propagation.combine import action_nodes, inverse_variance, robust, single
from pipps.propagation.cost_terms import density_estimation_costs, plain_costs, shaped_costs
from pipps.propagation.estimators import (
    ESTIMATORS,
    NAMED,
    compose,
    estimator,
    estimator_table,
    from_spec,
    parse_spec,
    spec_label,
    thesis_estimator,
)
from pipps.propagation.parts import biw_lr, density_lr, pathwise, plain_lr
from pipps.propagation.schedules import CrossFitted, cross_fitted, one_sweep
from pipps.propagation.weights import WEIGHT_SOURCES, FixedWeight

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "pipps"
PROPAGATION = PACKAGE / "propagation"

BUILT_IN = {
    pieces.CostTerms: [plain_costs(), shaped_costs(), density_estimation_costs("previous"), density_estimation_costs("none")],
    pieces.GradientPart: [pathwise(), biw_lr("previous"), biw_lr("thesis"), biw_lr("none"), plain_lr(),
                          density_lr("previous"), density_lr("none")],
    pieces.Combiner: [single(), inverse_variance(), robust(), action_nodes()],
    pieces.WeighsTwoParts: [inverse_variance(), robust(), action_nodes()],
    pieces.WeightSource: [factory() for factory in WEIGHT_SOURCES.values()] + [FixedWeight(0.3)],
    pieces.Schedule: [one_sweep(), CrossFitted()],
}


def _protocol_methods(protocol) -> dict[str, inspect.Signature]:
    names = [n for n, v in vars(protocol).items() if callable(v) and not n.startswith("_")]
    for base in protocol.__mro__[1:]:
        if base is not typing.Protocol and getattr(base, "_is_protocol", False):
            names += [n for n in _protocol_methods(base)]
    return {n: inspect.signature(getattr(protocol, n)) for n in dict.fromkeys(names)}


def _parameters(sig: inspect.Signature) -> list[tuple[str, object]]:
    return [(p.name, p.kind) for p in sig.parameters.values() if p.name != "self"]


@pytest.mark.parametrize("protocol, piece", [(p, x) for p, xs in BUILT_IN.items() for x in xs],
                         ids=lambda v: getattr(v, "__name__", type(v).__name__))
def test_every_built_in_piece_is_its_kind(protocol, piece):
    assert isinstance(piece, protocol)
    for name, want in _protocol_methods(protocol).items():
        got = inspect.signature(getattr(type(piece), name))
        assert _parameters(got) == _parameters(want), f"{type(piece).__name__}.{name}{got} is not {protocol.__name__}.{name}{want}"


def test_the_protocol_check_can_fail():
    class NotAPart:
        kind = "pathwise"
        cold_start = False

        def init(self, context):
            return ()

        def zeta(self, inputs, config):  # the state is missing
            return None

    assert isinstance(NotAPart(), pieces.GradientPart)  # the runtime check sees the names only...
    with pytest.raises(AssertionError, match="is not GradientPart.zeta"):
        test_every_built_in_piece_is_its_kind(pieces.GradientPart, NotAPart())  # ...the signatures catch it


@pytest.mark.parametrize("est", [e.estimator for e in ESTIMATORS.values()] + [e.thesis for e in ESTIMATORS.values() if e.thesis]
                         + [estimator("tp", k_lr="cross_fit"), estimator("tpx", k_lr="moving_average")])
def test_every_registered_estimator_is_made_of_the_kinds(est):
    assert isinstance(est.costs, pieces.CostTerms) and isinstance(est.combiner, pieces.Combiner)
    assert all(isinstance(p, pieces.GradientPart) for p in est.parts) and isinstance(est.schedule, pieces.Schedule)
    if est.combiner.num_parts == 2:
        assert isinstance(est.combiner, pieces.WeighsTwoParts) and isinstance(est.combiner.source, pieces.WeightSource)


# -- imports: no cycle in pipps/propagation ----------------------------------------------------------------


def _module_of(path: Path) -> str:
    return ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(".__init__")


def _imports(path: Path, package_root: Path) -> set[str]:
    """Every pipps module ``path`` imports, anywhere in the file (functions and ``if TYPE_CHECKING`` too)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            base = package_root.parent / node.module.replace(".", "/")
            out |= {f"{node.module}.{a.name}" if (base / f"{a.name}.py").exists() or (base / a.name).is_dir()
                    else node.module for a in node.names}
    return {m for m in out if m.startswith("pipps.")}


def import_graph(package_root: Path, sub: str) -> dict[str, set[str]]:
    """Module → the modules of ``sub`` it imports, for the modules of ``sub`` (e.g. "pipps.propagation")."""
    files = sorted((package_root / sub.removeprefix("pipps.").replace(".", "/")).rglob("*.py"))
    modules = {".".join(f.relative_to(package_root.parent).with_suffix("").parts).removesuffix(".__init__"): f for f in files}
    return {m: {t for t in _imports(f, package_root) if t in modules and t != m} for m, f in modules.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` as a list of modules (first = last), or None."""
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(m):
        state[m] = 1
        path.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                return path[path.index(t):] + [t]
            if t not in state and (found := visit(t)):
                return found
        state[m] = 2
        path.pop()
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_propagation_has_no_import_cycle():
    graph = import_graph(PACKAGE, "pipps.propagation")
    graph.pop("pipps.propagation", None)  # the package's __init__ re-exports; nothing in it imports it back
    assert "pipps.propagation.estimators" in graph and graph["pipps.propagation.estimators"]
    assert find_cycle(graph) is None, f"import cycle: {' → '.join(find_cycle(graph))}"


def test_the_cycle_check_finds_a_planted_cycle(tmp_path):
    """A function-local import that closes a loop (as config.py → cross_fit.py → config.py once did) is found."""
    pkg = tmp_path / "pipps" / "propagation"
    pkg.mkdir(parents=True)
    (tmp_path / "pipps" / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pipps.propagation.b import f\n")
    (pkg / "b.py").write_text("def f():\n    from pipps.propagation import a\n    return a\n")
    (pkg / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pipps.propagation.c2 import x\n")
    (pkg / "c2.py").write_text("import pipps.propagation.c\n")
    graph = import_graph(tmp_path / "pipps", "pipps.propagation")
    graph.pop("pipps.propagation", None)
    cycle = find_cycle(graph)
    assert cycle is not None and set(cycle) == {"pipps.propagation.a", "pipps.propagation.b"}
    del graph["pipps.propagation.a"], graph["pipps.propagation.b"]
    graph = {m: t - {"pipps.propagation.a", "pipps.propagation.b"} for m, t in graph.items()}
    assert set(find_cycle(graph)) == {"pipps.propagation.c", "pipps.propagation.c2"}


# -- no type tests on estimators outside the composition ---------------------------------------------------

#: the composition: the one module that may ask a piece for its class (to translate the named settings)
COMPOSITION = {"pipps.propagation.estimators"}


def _propagation_classes() -> set[str]:
    names = set()
    for f in PROPAGATION.glob("*.py"):
        names |= {n.name for n in ast.walk(ast.parse(f.read_text())) if isinstance(n, ast.ClassDef)}
    return names - {n for n in vars(pieces) if n[0].isupper() and isinstance(getattr(pieces, n), type)
                    and getattr(getattr(pieces, n), "_is_protocol", False)}  # a protocol is an interface, not a type


def _type_tests(tree: ast.AST, classes: set[str]) -> list[str]:
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("isinstance", "issubclass"):
            for n in ast.walk(node.args[1]):
                name = n.id if isinstance(n, ast.Name) else n.attr if isinstance(n, ast.Attribute) else None
                if name in classes:
                    found.append(f"line {node.lineno}: {name}")
    return found


def test_no_type_test_on_an_estimator_outside_the_composition():
    classes = _propagation_classes()
    assert {"Estimator", "CrossFitted", "BiwLR", "InverseVariance", "PreviousWeight"} <= classes
    offenders = {}
    for f in sorted(PACKAGE.rglob("*.py")):
        if _module_of(f) not in COMPOSITION and (found := _type_tests(ast.parse(f.read_text()), classes)):
            offenders[_module_of(f)] = found
    assert offenders == {}
    planted = ast.parse("if isinstance(estimator, CrossFitted):\n    pass\n")  # the check can fail
    assert _type_tests(planted, classes) == ["line 1: CrossFitted"]


# -- the registry -----------------------------------------------------------------------------------------


def _doc_table(text: str) -> str:
    start, end = "<!-- estimator-table: generated by pipps.propagation.estimators.estimator_table -->\n", "<!-- /estimator-table -->"
    assert start in text and end in text, "docs/estimators.md must hold the generated table between its markers"
    return text.split(start, 1)[1].split(end, 1)[0]


def test_the_docs_table_is_the_registrys():
    """docs/estimators.md's estimator table is generated from the registry: regenerate it with
    ``python -c "from pipps.propagation.estimators import estimator_table; print(estimator_table())"``."""
    assert _doc_table((ROOT / "docs" / "estimators.md").read_text()) == estimator_table()
    for e in ESTIMATORS.values():
        assert f"| `{e.name}` | {e.label} |" in estimator_table()


def test_the_registry_is_what_the_studies_and_the_cli_read():
    from pipps.cli import build_parser
    from pipps.studies import figures
    from pipps.studies.gradients import LABELS

    assert len({e.colour for e in ESTIMATORS.values()}) == len(ESTIMATORS)  # one colour each
    assert LABELS == {n: e.label for n, e in ESTIMATORS.items()}
    assert figures.COLORS == {n: e.colour for n, e in ESTIMATORS.items()}
    for n, e in ESTIMATORS.items():
        assert figures._color(n) == e.colour and figures._label(n) == e.label
        assert figures._label(f"{n} (variance tol 0.01)") == f"{e.label} (variance tol 0.01)"
    assert figures._color("tp:k_lr=previous") != figures._color("tp")
    study = build_parser()._subparsers._group_actions[0].choices["study"]
    variance = study._subparsers._group_actions[0].choices["variance"]
    help_text = next(a.help for a in variance._actions if "--estimators" in a.option_strings)
    assert all(f"{n}: {e.label}" in help_text for n, e in ESTIMATORS.items())


def test_the_thesis_variants_are_where_the_thesis_chose_otherwise():
    for n, e in ESTIMATORS.items():
        assert estimator(n) == e.estimator and thesis_estimator(n) == (e.thesis or e.estimator)
        assert e.thesis is None or e.thesis != e.estimator
    assert {n for n, e in ESTIMATORS.items() if e.thesis} == {"lr", "tp", "gtp", "glr", "del"}


@pytest.mark.parametrize("spec, want", [
    ("tp", estimator("tp")),
    ("tp:k_lr=previous", estimator("tp", k_lr="previous")),
    ("tp:k_lr=0.25:messages=pathwise", estimator("tp", k_lr=0.25, messages="pathwise")),
    ("tpx:k_lr=cross_fit", cross_fitted(estimator("tpx", k_lr="batch"))),
    ("lr:baseline=none", estimator("lr", baseline="none")),
])
def test_a_spec_is_the_estimator_its_settings_give(spec, want):
    assert from_spec(spec) == want
    name, settings = parse_spec(spec)
    assert from_spec(spec, "thesis") == thesis_estimator(name, **settings)


def test_a_spec_is_labelled_and_refused_by_name():
    assert spec_label("tp") == "TP" and spec_label("tp:k_lr=previous") == "TP (k_lr=previous)"
    assert spec_label("tp:k_lr=0.25") == "TP (k_lr=0.25)"
    with pytest.raises(ValueError, match="unknown estimator 'tq'"):
        from_spec("tq")
    with pytest.raises(ValueError, match="expected NAME or NAME:SETTING=VALUE"):
        from_spec("tp:k_lr")
    with pytest.raises(ValueError, match="unknown estimator settings"):
        from_spec("tp:kl=0.5")
    assert set(NAMED) == set(ESTIMATORS)


def test_an_estimator_fits_a_density_exactly_when_one_of_its_pieces_does():
    """``Estimator.fits_density`` (what the CLI's particle check asks) comes from the pieces: DEL's
    cost terms and LR part fit a Gaussian to the particles; no other registered estimator does,
    in either variant."""
    for entry in ESTIMATORS.values():
        for est in (entry.estimator, entry.thesis or entry.estimator):
            assert est.fits_density == (entry.name in ("del", "del_cost")), entry.name
    assert compose(density_estimation_costs(baseline="none"), pathwise()).fits_density
    assert compose(plain_costs(), density_lr()).fits_density
    assert not compose(shaped_costs(), pathwise(), biw_lr(), combiner=inverse_variance()).fits_density
