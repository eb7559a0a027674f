"""Experiments built on the pipeline: the paper's ablations on the demo scene (``n2f2 bench``).

* :mod:`.variants`: the fields the bench trains and the paper's step sizes at a smaller D;
* :mod:`.config`: its settings and the data every variant trains on;
* :mod:`.bench`: that data (through the pipeline's stages and cache) and the run;
* :mod:`.training`: training a variant, with resume and continuation of shorter runs;
* :mod:`.memory`: activation and parameter memory of training;
* :mod:`.evaluate`: the protocol, the per-level cosine and the composite-weight statistics;
* :mod:`.timing`: the query-time breakdown;
* :mod:`.claims`: the paper's claims with paired standard errors and verdicts;
* :mod:`.report`: ``bench.md`` and the plots.
"""

from __future__ import annotations

from .._lazy import lazy_exports

__getattr__, __all__ = lazy_exports(
    __name__,
    {
        "BenchConfig": "config",
        "BenchData": "config",
        "run_bench": "bench",
        "VARIANTS": "variants",
        "VariantSpec": "variants",
        "run_name": "variants",
        "scaled_step": "variants",
        "train_variant": "training",
        "ActivationMeter": "memory",
        "paired_difference": "claims",
        "convergence": "claims",
    },
)
