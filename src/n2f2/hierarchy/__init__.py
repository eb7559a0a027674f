"""The scene's hierarchy (``n2f2 decompose``): every Gaussian placed in one tree of parts,
objects and groups read off the trained nested field, without text (:mod:`.build`); the
nodes' embeddings and phrases (:mod:`.nodes`), the folder's files (:mod:`.files`) and per-view
node id maps (:mod:`.views`). Node queries (``--mode node``) answer with its nodes.

Importing this package is cheap and has no side effects."""

from .._lazy import lazy_exports

__getattr__, __all__ = lazy_exports(
    __name__,
    {
        "DecomposeConfig": "build",
        "Decomposition": "build",
        "decompose": "build",
        "LoadedTree": "files",
        "read_tree": "files",
        "node_id_maps": "views",
        "DecomposeJob": "stage",
        "run_decompose": "stage",
    },
)
