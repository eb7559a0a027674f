"""The field's variants as objects (n2f2.field.variants): each variant's scales, labels, step rule and
modes against hand-worked answers, the masks the field trains with, and the string in files."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from n2f2.field import FieldConfig, NestedField, load_field, save_field
from n2f2.field.model import VARIANTS as VARIANT_NAMES
from n2f2.field.variants import VARIANTS, FieldVariant, get_variant
from n2f2.query.engine import QueryEngine
from n2f2.segments.bins import scale_to_dims, supervised_dims

NESTED, FLAT, LEVELS = VARIANTS["nested"], VARIANTS["flat"], VARIANTS["levels"]


def tiny_field(variant: str, dim: int, step_size: int = 1) -> NestedField:
    cfg = FieldConfig(backbone="mlp", dim=dim, hidden=8, pe_frequencies=1, variant=variant, step_size=step_size)
    return NestedField(cfg, 4, np.zeros(3), np.ones(3))


def test_registry_names_and_lookup():
    assert list(VARIANTS) == ["nested", "flat", "levels"]
    assert VARIANT_NAMES == ("nested", "flat", "levels")  # FieldConfig's choices come from the registry
    for name, v in VARIANTS.items():
        assert isinstance(v, FieldVariant) and v.name == name and get_variant(name) is v
    with pytest.raises(ValueError, match="nested"):
        get_variant("deep")


# ---------------------------------------------------------------------------------- scales by hand
def test_nested_scales_are_the_prefixes_k_2k_up_to_k_floor_D_over_k():
    # D = 8, k = 2: floor(8 / 2) = 4 scales, prefixes 2, 4, 6, 8.
    assert NESTED.scale_dims(8, 2) == [2, 4, 6, 8]
    assert NESTED.scales(8, 2) == [(0, 2), (0, 4), (0, 6), (0, 8)]
    assert NESTED.scale_labels(8, 2) == ["d=2", "d=4", "d=6", "d=8"]
    assert NESTED.step(8, 2) == 2
    # D = 10, k = 3: floor(10 / 3) = 3 scales, 3, 6, 9; dim 10 belongs to no scale.
    assert NESTED.scale_dims(10, 3) == [3, 6, 9]
    # k = 1: every prefix is a scale (the paper's D scales).
    assert NESTED.scale_dims(5, 1) == [1, 2, 3, 4, 5]
    # paper Table 6, D = 512, k = 170: 3 scales.
    assert NESTED.scale_dims(512, 170) == [170, 340, 510]
    with pytest.raises(ValueError):
        NESTED.scale_dims(4, 5)


def test_flat_has_one_scale_all_D_dims_whatever_the_step():
    for k in (1, 3):
        assert FLAT.step(8, k) == 8
        assert FLAT.scales(8, k) == [(0, 8)]
        assert FLAT.scale_labels(8, k) == ["d=8"]


def test_levels_has_three_blocks_part_last():
    # D = 12: blocks [0, 4) [4, 8) [8, 12); part (level 0) reads the last block, group the first.
    assert LEVELS.scales(12) == [(8, 12), (4, 8), (0, 4)]
    assert LEVELS.scale_labels(12) == ["part", "object", "group"]
    # D = 10: edges round(0), round(10/3) = 3, round(20/3) = 7, 10.
    assert LEVELS.scales(10) == [(7, 10), (3, 7), (0, 3)]
    # D = 128: edges 0, round(42.67) = 43, round(85.33) = 85, 128.
    assert LEVELS.scales(128) == [(85, 128), (43, 85), (0, 43)]
    assert LEVELS.step(12, 1) == 1  # recorded as configured, not used


def test_step_rules():
    assert NESTED.uses_step and not FLAT.uses_step and not LEVELS.uses_step
    # the step size a field is trained with when the bench asks for k = 8
    assert (NESTED.step_size(8), FLAT.step_size(8), LEVELS.step_size(8)) == (8, 1, 1)
    for v in VARIANTS.values():  # step() may be given the configured or the effective step
        for D, k in ((8, 1), (8, 2), (12, 3)):
            assert v.step(D, v.step(D, k)) == v.step(D, k)


def test_modes_and_what_oracle_picks_among():
    assert NESTED.modes == FLAT.modes == ("composite", "explicit", "soft", "oracle")
    assert LEVELS.modes == ("levels", "oracle")
    assert (NESTED.answers_with, FLAT.answers_with, LEVELS.answers_with) == ("prefix", "prefix", "levels")
    assert [NESTED.mode_for(m) for m in ("composite", "explicit", "oracle")] == ["composite", "explicit", "oracle"]
    assert [LEVELS.mode_for(m) for m in ("composite", "explicit", "oracle")] == [None, "levels", "oracle"]


# ---------------------------------------------------------------------------------- against the field
def test_nested_scales_are_the_values_of_M_s_and_the_field_masks():
    s = torch.linspace(0.0, 0.999, 997)
    for D, k in ((8, 2), (10, 3), (12, 1)):
        assert sorted(set(scale_to_dims(s, D, k).tolist())) == NESTED.scale_dims(D, k)
        field = tiny_field("nested", D, k)
        ones = field.supervision_mask(s).sum(dim=1).long().tolist()
        assert sorted(set(ones)) == NESTED.scale_dims(D, k)
    flat = tiny_field("flat", 8, 1)
    assert flat.supervision_mask(s).sum(dim=1).unique().tolist() == [8]


def test_levels_scales_are_the_field_level_masks():
    field = tiny_field("levels", 10)
    mask = field.level_mask(torch.tensor([0, 1, 2]))  # part, object, group
    for row, (a, b) in zip(mask, LEVELS.scales(10)):
        assert torch.nonzero(row).squeeze(1).tolist() == list(range(a, b))


# ---------------------------------------------------------------------------------- files keep the name
def test_config_and_field_expose_the_object_and_files_keep_the_string(tmp_path):
    cfg = FieldConfig.from_dict({"variant": "levels", "dim": 12, "backbone": "mlp"})  # as read from a file
    assert cfg.kind is LEVELS and cfg.to_dict()["variant"] == "levels"
    field = tiny_field("flat", 6)
    assert field.kind is FLAT
    save_field(tmp_path / "field.pt", field)
    loaded, meta = load_field(tmp_path / "field.pt")
    assert meta["variant"] == meta["config"]["variant"] == "flat" and loaded.kind is FLAT


def test_query_engine_reads_the_variant_from_the_metadata():
    nested = tiny_field("nested", 8, 2)
    eng = QueryEngine(nested, None, None, {"config": nested.config.to_dict()})
    assert eng.kind is NESTED and eng.step == 2 and eng.scale_labels == ["d=2", "d=4", "d=6", "d=8"]
    assert eng.scale_dims == supervised_dims(8, 2) and eng._cache_kind("oracle") == "prefix"
    flat = tiny_field("flat", 8)
    eng = QueryEngine(flat, None, None, {"config": flat.config.to_dict()})
    assert eng.step == 8 and eng.scale_labels == ["d=8"]
    levels = tiny_field("levels", 12)
    eng = QueryEngine(levels, None, None, {"variant": "levels", "config": {"dim": 12}})  # name outside config
    assert eng.kind is LEVELS and eng.modes() == ("levels", "oracle") and eng._cache_kind("oracle") == "levels"
    assert eng.scale_labels == ["part", "object", "group"]
    old = QueryEngine(nested, None, None, {})  # metadata naming no variant: a nested field, k = 1
    assert old.kind is NESTED and old.step == 1 and len(old.scale_labels) == 8


def test_bench_variants_follow_the_field_variant():
    from n2f2.experiments.variants import VARIANTS as BENCH
    from n2f2.experiments.variants import run_name, variant_field_config

    assert [run_name(BENCH[v], 128) for v in ("k8", "flat", "levels")] == ["nested-k2", "flat", "levels"]
    assert variant_field_config(BENCH["k32"], 128).step_size == 8  # 512 / 32 = 16 scales -> k = 128 / 16
    assert variant_field_config(BENCH["levels"], 128).step_size == 1
    assert BENCH["flat"].kind is FLAT
