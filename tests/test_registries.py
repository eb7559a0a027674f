"""The query modes and the field variants are objects in registries (n2f2.query.modes,
n2f2.field.variants): outside those two modules no code compares a value with a mode's or a
variant's name. The check parses every module of ``src/n2f2`` with ``ast`` and is itself tried on
a small fake module whose switches are known by hand. Then the mode registry: its names, lookup,
what each mode says against hand-worked answers, and the engine answering each mode as its object
says."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from test_query import E_TEST, HashEncoder, engine, run_dir  # noqa: F401 (engine, run_dir: fixtures)

import n2f2
from n2f2.errors import InputError
from n2f2.field.variants import VARIANTS
from n2f2.query.modes import CACHE_KINDS, CHOICES, MODES, QUERY_MODES, QueryMode, get_mode

PACKAGE_ROOT = Path(n2f2.__file__).parent
# Where the names may be compared: the registries themselves, and the evaluation protocols' (their names).
REGISTRIES = ("query/modes.py", "field/variants.py", "eval/protocols.py")


def _literals(node: ast.expr) -> list[str]:
    """The strings of a string literal, or of a tuple / list / set of literals."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return [node.value]
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return [e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
    return []


def name_switches(source: str, names: set[str]) -> list[tuple[int, str, list[str]]]:
    """``(line, operator, names)`` of every comparison in ``source`` that tests a value against a
    literal naming one of ``names``: ``x == "a"``, ``"a" != x``, ``x in ("a", "b")``,
    ``x not in {"a"}`` (chained comparisons pair by pair). ``"a" in results`` asks whether results
    hold an entry named ``a`` (a lookup, as a report's table does) and is not a switch."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Compare):
            continue
        operands = [node.left, *node.comparators]
        for op, left, right in zip(node.ops, operands, operands[1:]):
            if isinstance(op, (ast.Eq, ast.NotEq)):
                literals = _literals(left) + _literals(right)
            elif isinstance(op, (ast.In, ast.NotIn)):
                literals = _literals(right)
            else:
                continue
            hits = sorted(set(literals) & names)
            if hits:
                found.append((node.lineno, type(op).__name__, hits))
    return sorted(found)


def package_switches(root: Path, names: set[str], allowed: tuple[str, ...]) -> list[str]:
    """``path:line: operator names`` of every switch on ``names`` in the package at ``root``
    outside the files ``allowed`` (paths relative to ``root``)."""
    out = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel not in allowed:
            out += [f"{rel}:{line}: {op} {hits}" for line, op, hits in name_switches(path.read_text(), names)]
    return out


def test_no_code_switches_on_a_mode_or_variant_name():
    assert package_switches(PACKAGE_ROOT, set(MODES) | set(VARIANTS), REGISTRIES) == []


FAKE = """\
def answer(mode, kind, modes, rows, a, b):
    if mode == "composite":
        pass
    if "soft" != mode or kind in ("oracle", "prefix"):
        pass
    if mode not in {"levels"} and a < b == "flat":
        pass
    if mode == "prefix" or kind in ("prefix", "linear") or mode == MODE.name:
        pass
    if "explicit" in rows or mode is None:
        return {"nested": 1}
    return [m for m in modes if m in ["nested", "node"]]
"""


def test_the_check_finds_each_kind_of_switch():
    """By hand: lines 2, 4 (twice), 6 (twice) and 12 compare with a name; line 8 compares with
    literals that name nothing, line 10 looks an entry up, line 11 is no comparison."""
    assert name_switches(FAKE, {"composite", "soft", "oracle", "levels", "flat", "nested"}) == [
        (2, "Eq", ["composite"]),
        (4, "In", ["oracle"]),
        (4, "NotEq", ["soft"]),
        (6, "Eq", ["flat"]),
        (6, "NotIn", ["levels"]),
        (12, "In", ["nested"]),
    ]


def test_the_check_skips_only_the_registries(tmp_path):
    (tmp_path / "query").mkdir()
    (tmp_path / "query" / "modes.py").write_text("ok = mode == 'soft'\n")
    (tmp_path / "query" / "engine.py").write_text("x = 1\nbad = mode in ('soft',)\n")
    assert package_switches(tmp_path, {"soft"}, ("query/modes.py",)) == ["query/engine.py:2: In ['soft']"]


# ---------------------------------------------------------------------------------- the registry
def test_every_mode_name_has_its_object_in_order():
    from n2f2.query.engine import MODES as ENGINE_MODES

    assert MODES == ("composite", "explicit", "levels", "soft", "oracle", "node")
    assert ENGINE_MODES is MODES and tuple(QUERY_MODES) == MODES
    for name in MODES:
        m = get_mode(name)
        assert isinstance(m, QueryMode) and m.name == name and QUERY_MODES[name] is m
        assert m.description and "\n" not in m.description
        with pytest.raises(dataclasses.FrozenInstanceError):
            m.name = "other"  # type: ignore[misc]


@pytest.mark.parametrize("name", ["deep", "", "Composite", None])
def test_an_unknown_mode_is_an_input_error_naming_the_modes(name):
    with pytest.raises(InputError) as e:
        get_mode(name)  # type: ignore[arg-type]
    assert str(e.value) == f"unknown query mode {name!r}; choose one of composite, explicit, levels, soft, oracle, node"


def test_each_mode_against_hand_worked_answers():
    table = {  # choice, cache, per scale, from scales, blends, truth, 3D, npy, paper, viewer
        "composite": ("none", "composite", False, False, False, False, True, True, True, True),
        "explicit": ("select", "prefix", True, True, False, False, True, False, True, True),
        "levels": ("select", "levels", True, True, False, False, True, True, False, True),
        "soft": ("blend", None, False, True, True, False, True, False, False, False),
        "oracle": ("truth", None, True, True, False, True, False, False, True, False),
        "node": ("none", "nodes", False, False, False, False, True, False, False, True),
    }
    for name, want in table.items():
        m = QUERY_MODES[name]
        got = (m.choice, m.cache_kind, m.per_scale, m.from_scales, m.blends, m.needs_truth, m.in_3d, m.writes_npy,
               m.paper, m.viewer)
        assert got == want, name
    nested, flat, levels = VARIANTS["nested"], VARIANTS["flat"], VARIANTS["levels"]
    assert [QUERY_MODES["oracle"].cache_for(v) for v in (nested, flat, levels)] == ["prefix", "prefix", "levels"]
    assert QUERY_MODES["soft"].cache_for(nested) == "prefix" and QUERY_MODES["levels"].cache_for(nested) == "levels"


def test_the_variants_of_a_mode_are_those_that_answer_it():
    assert QUERY_MODES["composite"].variants == ("nested", "flat")
    assert QUERY_MODES["soft"].variants == ("nested", "flat")
    assert QUERY_MODES["levels"].variants == ("levels",)
    assert QUERY_MODES["oracle"].variants == ("nested", "flat", "levels")
    assert QUERY_MODES["node"].variants == ("nested", "flat", "levels")  # from the run's hierarchy
    for v in VARIANTS.values():  # a variant answers only registered modes, in the registry's order
        assert [m for m in MODES if m in v.modes] == sorted(v.modes, key=MODES.index)
        assert set(v.modes) <= set(MODES)


def test_the_engine_has_each_method_a_mode_names():
    from n2f2.query.engine import QueryEngine

    for m in QUERY_MODES.values():
        assert callable(getattr(QueryEngine, m.view_query)), m.name
        assert m.gaussian_query is None or callable(getattr(QueryEngine, m.gaussian_query)), m.name


def test_a_mode_checks_its_settings():
    with pytest.raises(ValueError, match="choice"):
        QueryMode("x", "x", "guess", None, "_view_soft")
    with pytest.raises(ValueError, match="cache kind"):
        QueryMode("x", "x", "none", "tree", "_view_composite")
    assert set(CHOICES) == {m.choice for m in QUERY_MODES.values()}
    assert set(CACHE_KINDS) == {m.cache_kind for m in QUERY_MODES.values()} - {None}


# ---------------------------------------------------------------------------------- the engine
def _levels_engine(engine):  # noqa: F811 (the fixture)
    from n2f2.field import FieldConfig, NestedField
    from n2f2.query import QueryConfig, QueryEngine

    torch.manual_seed(1)
    field = NestedField(FieldConfig(backbone="mlp", dim=12, hidden=16, pe_frequencies=2, variant="levels"),
                        E_TEST, engine.field.bbox_min.numpy(), engine.field.bbox_max.numpy())
    with torch.no_grad():
        field.W.copy_(torch.randn(E_TEST, 12) / 3.0)
    return QueryEngine(field, engine.gaussians, HashEncoder(E_TEST), {"config": field.config.to_dict()},
                       QueryConfig(selection="max", render="gaussians"), scene=engine.scene)


def test_the_engine_answers_each_mode_as_its_object_says(engine):  # noqa: F811 (the fixture)
    """On a nested and a levels field, every mode each answers: a per-scale mode's map is the
    chosen scale's map of its cache, bit for bit; a blend is soft_relevancy of every scale's; a
    mode of its own is its cache's one map; ground truth is asked for only where it is needed;
    over the Gaussians, the same, or an InputError for a mode with no 3D query."""
    from n2f2.query.soft import soft_relevancy

    texts = ["teapot", "lid", "red mug"]
    for eng in (engine, _levels_engine(engine)):
        view = eng.render_view(0, modes=list(eng.modes()), rgb=False)
        emb = eng.encode(texts)
        for name in eng.modes():
            m = get_mode(name)
            cache = view.caches[m.cache_for(eng.kind)]
            S = len(cache.labels)
            every = cache.relevancy(emb).view(S, len(texts), view.height, view.width)
            scorer = None
            if m.needs_truth:
                with pytest.raises(InputError, match="ground-truth masks or a scorer"):
                    eng.query(view, texts, name)
                scorer = lambda maps, qi: np.arange(len(maps)) == qi % len(maps)  # noqa: E731
            res = eng.query(view, texts, name, scorer=scorer)
            assert res.mode == name and res.scale_labels == cache.labels
            if m.per_scale:
                assert all(isinstance(c, int) for c in res.chosen)
                if m.needs_truth:
                    assert res.chosen == [q % S for q in range(len(texts))]
                for q, c in enumerate(res.chosen):
                    assert torch.equal(res.relevancy[q], every[c, q])
            else:
                assert res.chosen == [None] * len(texts)
                if m.blends:
                    soft, peaks = soft_relevancy(every.reshape(S, len(texts), -1))
                    assert torch.equal(res.relevancy, soft.view(len(texts), view.height, view.width))
                    assert torch.equal(res.scale_scores, peaks)
                else:
                    assert S == 1 and torch.equal(res.relevancy, every[0])
            if not m.in_3d:
                with pytest.raises(InputError, match="no 3D query"):
                    eng.query_gaussians(texts, name)
                continue
            res3 = eng.query_gaussians(texts, name)
            assert res3.relevancy.shape == (len(texts), len(eng.gaussians.means))
            assert all((c is not None) == m.per_scale for c in res3.chosen)


# ---------------------------------------------------------------------------------- the variants' supervision
def test_each_variant_says_what_a_scale_supervises():
    """By hand, D = 6: nested k = 2 supervises prefixes 2, 4, 6 (M(s) = 2 ceil(3 (1 - s))); flat
    all 6 dims; levels the block of the scale's tercile, [4, 6) for s < 1/3 (part), [0, 2) for
    s >= 2/3 (group)."""
    nested, flat, levels = VARIANTS["nested"], VARIANTS["flat"], VARIANTS["levels"]
    assert (nested.prefix, flat.prefix, levels.prefix) == (True, True, False)
    s = torch.tensor([0.0, 0.3, 0.5, 0.9])
    assert nested.dims_for_scale(s, 6, 2).tolist() == [6, 6, 4, 2]
    assert flat.dims_for_scale(s, 6, 2).tolist() == [6, 6, 6, 6]
    with pytest.raises(ValueError, match="'levels' variant has no prefix M"):
        levels.dims_for_scale(s, 6)
    ones = [[1.0] * 6, [1.0] * 6, [1.0] * 4 + [0.0] * 2, [1.0] * 2 + [0.0] * 4]
    assert nested.supervision_mask(s, 6, 2).tolist() == ones
    assert flat.supervision_mask(s, 6, 2).tolist() == [[1.0] * 6] * 4
    part, obj, group = [0.0] * 4 + [1.0] * 2, [0.0] * 2 + [1.0] * 2 + [0.0] * 2, [1.0] * 2 + [0.0] * 4
    assert levels.supervision_mask(s, 6).tolist() == [part, part, obj, group]
    for v in VARIANTS.values():
        assert v.supervision_mask(s, 6, 2).dtype == torch.float32


def test_the_field_asks_its_variant():
    from n2f2.field import FieldConfig, NestedField

    s = torch.rand(40, generator=torch.Generator().manual_seed(0))
    for name, v in VARIANTS.items():
        cfg = FieldConfig(backbone="mlp", dim=9, hidden=8, pe_frequencies=1, variant=name, step_size=3)
        field = NestedField(cfg, 4, np.zeros(3), np.ones(3))
        assert torch.equal(field.supervision_mask(s), v.supervision_mask(s, 9, 3))
        if v.prefix:
            assert torch.equal(field.dims_for_scale(s), v.dims_for_scale(s, 9, 3))
