"""``b3dgs-view``: a local web viewer (viser) of a finished run, its renders and its uncertainty.

:mod:`b3dgs.viewer.modes` renders the modes (no viser needed), :mod:`b3dgs.viewer.cameras` converts between
the browser's camera and b3dgs cameras, :mod:`b3dgs.viewer.run` opens a run dir with one-line errors,
:mod:`b3dgs.viewer.server` is the viser app and :mod:`b3dgs.viewer.app` the console entry point.
"""
