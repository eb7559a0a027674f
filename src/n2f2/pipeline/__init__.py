"""The pipeline layer between the stages and the command line: the content-keyed stage cache
(:mod:`.cache`), the named presets of every stage's settings (:mod:`.presets`), ``n2f2 run`` /
``demo`` (:mod:`.run`, each stage through its own runner, e.g. :func:`n2f2.gaussians.stage.run_fit`)
and ``run-many`` (:mod:`.many`), with the checks before their first stage (:mod:`.preflight`) and
each stage's expected time (:mod:`.estimate`), which ``n2f2 doctor`` prints (:mod:`.doctor`); their
options are in :mod:`.commands`."""

from __future__ import annotations

from .._lazy import lazy_exports

__getattr__, __all__ = lazy_exports(
    __name__,
    {
        "StageCache": "cache",
        "file_digest": "cache",
        "scene_digest": "cache",
        "stage_key": "cache",
        "tree_digest": "cache",
        "Preset": "presets",
        "PRESETS": "presets",
        "get_preset": "presets",
        "DemoScene": "run",
        "RunOptions": "run",
        "resolve_defaults": "run",
        "run_pipeline": "run",
        "run_many": "many",
        "run_scene": "many",
    },
)
