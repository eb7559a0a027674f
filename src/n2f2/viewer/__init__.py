"""Live viewer: a local web page and JSON API over a trained run (see ``viewer.server``)."""
