"""n2f2: Nested Neural Feature Fields (N2F2, ECCV 2024) for hierarchical open-vocabulary 3D scenes.

Data flow, one module per stage:
    cameras / data  ->  gaussians  ->  render  ->  segments  ->  field  ->  train
    ->  query  ->  eval  ->  viewer  ->  cli
"""

__version__ = "0.1.0"
