"""Studies built on training in rounds: the fixed-budget active-view study (``b3dgs-study active``)."""
