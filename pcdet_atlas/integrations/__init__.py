"""Bridges to other toolkits, one sub-package each (:mod:`pcdet_atlas.integrations.openpcdet`).

The top layer: an integration may use every layer of the package (attacks, datasets, scoring)
and none imports it; only tools and users do (``tests/test_import_graph.py``).
"""
