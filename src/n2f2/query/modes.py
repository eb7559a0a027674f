"""The query modes as objects, one per mode, so that the engine, the evaluation, the bench and the
viewers ask a mode what they need instead of switching on its name.

Every file that records a mode (``query.json``, ``eval.json``, ``bench.json``) keeps the name;
:data:`QUERY_MODES` maps the name to the object and :func:`get_mode` looks one up. What a mode
is made of:

* :attr:`~QueryMode.choice`: how a query gets its map: ``"none"`` (one map of its own, no scale),
  ``"select"`` (the scale with the highest selection score, LERF / LangSplat), ``"blend"`` (every
  scale weighted, :mod:`n2f2.query.soft`) or ``"truth"`` (the scale that best matches the ground
  truth); :attr:`~QueryMode.per_scale`, :attr:`~QueryMode.from_scales`, :attr:`~QueryMode.blends`
  and :attr:`~QueryMode.needs_truth` follow from it;
* :attr:`~QueryMode.cache_kind`: the score cache a view keeps for it (:mod:`n2f2.query.caches`),
  or None for the field's own (:attr:`n2f2.field.variants.FieldVariant.answers_with`: its prefixes
  or its level blocks), see :meth:`~QueryMode.cache_for`;
* :attr:`~QueryMode.view_query`, :attr:`~QueryMode.gaussian_query`: the
  :class:`~n2f2.query.engine.QueryEngine` methods that answer it on a rendered view and over the
  Gaussians (None: no 3D query);
* what the evaluation and the reports do with it (:attr:`~QueryMode.writes_npy`,
  :attr:`~QueryMode.paper`, :attr:`~QueryMode.viewer`).

Which field variants answer a mode is the variants' to say (:attr:`FieldVariant.modes`);
:attr:`QueryMode.variants` reads it back.

    mode       choice  cache      per scale  3D   .npy of the eval   paper  viewers
    composite  none    composite  no         yes  its map            yes    yes
    explicit   select  prefix     yes        yes  -                  yes    yes
    levels     select  levels     yes        yes  every level's map  -      yes
    soft       blend   field's    no         yes  -                  -      -
    oracle     truth   field's    yes        no   -                  yes    -
    node       none    nodes      no         yes  -                  -      yes

``node`` answers from the run's hierarchy (``n2f2 decompose``, :mod:`n2f2.query.nodes`): a run
offers it once that folder exists, whatever its variant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

from ..errors import InputError

if TYPE_CHECKING:
    from ..field.variants import FieldVariant

CHOICES = ("none", "select", "blend", "truth")  # QueryMode.choice (see the module docstring)
# Score caches (ViewCache.caches' keys): the composite Theta~, the prefixes of theta, the level
# blocks, the nodes of the run's hierarchy.
COMPOSITE_CACHE, PREFIX_CACHE, LEVELS_CACHE, NODE_CACHE = "composite", "prefix", "levels", "nodes"
CACHE_KINDS = (COMPOSITE_CACHE, PREFIX_CACHE, LEVELS_CACHE, NODE_CACHE)


@dataclass(frozen=True)
class QueryMode:
    """One query mode: how it answers a query and what the stages after the query do with it."""

    name: str  # as given on the command line and stored in files
    description: str  # one line for help texts
    choice: str  # how a query gets its map: one of CHOICES
    cache_kind: Optional[str]  # its score cache (one of CACHE_KINDS); None: the field's (cache_for)
    view_query: str  # the QueryEngine method answering it on a rendered view
    gaussian_query: Optional[str] = None  # the QueryEngine method answering it over the Gaussians; None: none
    writes_npy: bool = False  # the evaluation writes its relevancy .npy (per_scale: every scale's map)
    paper: bool = False  # one of the paper's modes (its Table 3): the bench report's columns and curves
    viewer: bool = False  # offered by the viewers
    needs_tree: bool = False  # answers from the run's hierarchy (`n2f2 decompose`), on any variant
    answers_sets: bool = False  # its answer over the Gaussians is a set (1 in it, 0 out): selected as it is

    def __post_init__(self) -> None:
        if self.choice not in CHOICES:
            raise ValueError(f"choice must be one of {CHOICES}, got {self.choice!r}")
        if self.cache_kind is not None and self.cache_kind not in CACHE_KINDS:
            raise ValueError(f"cache kind must be one of {CACHE_KINDS} or None, got {self.cache_kind!r}")

    @property
    def per_scale(self) -> bool:
        """Whether it answers a query with the map of one of its scales (chosen per query), so
        the evaluation keeps one map per protocol setting; otherwise one map per query."""
        return self.choice in ("select", "truth")

    @property
    def from_scales(self) -> bool:
        """Whether its map is made from the relevancy at every scale of the field."""
        return self.choice != "none"

    @property
    def blends(self) -> bool:
        """Whether its map is a weighted mean of every scale's (:mod:`n2f2.query.soft`)."""
        return self.choice == "blend"

    @property
    def needs_truth(self) -> bool:
        """Whether a query needs ground-truth masks or a scorer (an evaluation bound)."""
        return self.choice == "truth"

    @property
    def in_3d(self) -> bool:
        """Whether it answers queries over the Gaussians (no view, no ground truth)."""
        return self.gaussian_query is not None

    @property
    def variants(self) -> tuple[str, ...]:
        """The field variants that answer it (:attr:`n2f2.field.variants.FieldVariant.modes`;
        every variant for a mode that answers from the run's hierarchy)."""
        from ..field.variants import VARIANTS

        return tuple(v.name for v in VARIANTS.values() if self.name in v.modes or self.needs_tree)

    def cache_for(self, variant: FieldVariant) -> str:
        """The score cache it reads on a field of ``variant``."""
        return self.cache_kind or variant.answers_with

    def __repr__(self) -> str:
        return f"<query mode {self.name!r}>"


COMPOSITE = QueryMode(
    "composite",
    "one map per query from the composite embedding W Theta~ (paper Sec. 3.3, the default)",
    "none",
    COMPOSITE_CACHE,
    "_view_composite",
    "_gaussians_composite",
    writes_npy=True,
    paper=True,
    viewer=True,
)
EXPLICIT = QueryMode(
    "explicit",
    "per query the scale with the highest selection score (LERF / LangSplat)",
    "select",
    PREFIX_CACHE,
    "_view_selected",
    "_gaussians_selected",
    paper=True,
    viewer=True,
)
LEVELS = QueryMode(
    "levels",
    "per query the level of the 3-level field with the highest selection score (LangSplat)",
    "select",
    LEVELS_CACHE,
    "_view_selected",
    "_gaussians_selected",
    writes_npy=True,
    viewer=True,
)
SOFT = QueryMode(
    "soft",
    "every scale weighted by the softmax of its highest relevancy (n2f2.query.soft)",
    "blend",
    None,
    "_view_soft",
    "_gaussians_soft",
)
ORACLE = QueryMode(
    "oracle",
    "per query the scale that best matches the ground truth: the upper bound of scale selection",
    "truth",
    None,
    "_view_oracle",
    paper=True,
)
NODE = QueryMode(
    "node",
    "whole nodes of the run's hierarchy (n2f2 decompose): the best node and its instances (n2f2.query.nodes)",
    "none",
    NODE_CACHE,
    "_view_node",
    "_gaussians_node",
    viewer=True,
    needs_tree=True,
    answers_sets=True,
)

# The registry: mode name -> its mode. Order = the order of help texts, choices and reports.
QUERY_MODES: dict[str, QueryMode] = {m.name: m for m in (COMPOSITE, EXPLICIT, LEVELS, SOFT, ORACLE, NODE)}
MODES = tuple(QUERY_MODES)  # the names


def get_mode(name: str) -> QueryMode:
    """The mode named ``name`` (:class:`~n2f2.errors.InputError` naming the choices for an unknown one)."""
    try:
        return QUERY_MODES[name]
    except (KeyError, TypeError):
        raise InputError(None, f"unknown query mode {name!r}; choose one of {', '.join(MODES)}") from None
