"""Live viewer of a trained run: the Gaussians as splats in the browser with queries that
recolour them (``viewer.splats``, viser), and a JSON API with a 2D page (``viewer.server``)."""
