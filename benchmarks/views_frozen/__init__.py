"""A frozen copy of the views stage's synthesis as it was before the vectorised rasteriser and the
colour views (commit 7f31cd2: ``pipeline/views.py`` -> ``geometry.py``, ``pipeline/view_synthesis.py``
-> ``synthesis.py``, ``pipeline/stages/views.py`` -> ``stage.py``, imports pointed at ``pipeline``), so ``keystone bench views`` can time the old and
the new code side by side in one run and compare their outputs. Never imported by the product."""
