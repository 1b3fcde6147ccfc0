"""The optional parts of the package and the error that names the extra to install.

``pip install pyro_slam`` installs the core (model, inference, simulator, CLI, CARMEN logs,
occupancy-grid export). The extras add:

========================  ===============================================================
``[eval]``                evo: absolute trajectory error (ATE) in ``metrics.json`` and
                          :func:`pyro_slam.metrics.ate` / :func:`~pyro_slam.metrics.aligned_error`
``[ros]``                 rosbags: ROS 1 / ROS 2 bags (:func:`pyro_slam.io.read_rosbag`)
``[notebooks]``           JupyterLab, a kernel and evo for the tutorials in ``notebooks/``
``[docs]``                mkdocs and its plugins for the documentation site
``[dev]``                 pytest, hypothesis, ruff and the notebook runner of the test suite
========================  ===============================================================

A module that uses an optional package imports it once at module level, guarded (the name is
None when the package is missing), and calls :func:`require` where the feature is used.
"""

from __future__ import annotations


class MissingExtra(ImportError):
    """An optional package is not installed; the message names the extra that installs it."""

    def __init__(self, feature: str, package: str, extra: str):
        self.feature, self.package, self.extra = feature, package, extra
        super().__init__(
            f"{feature} needs the optional package {package!r}: pip install 'pyro_slam[{extra}]'"
        )


def require(module, feature: str, package: str, extra: str) -> None:
    """Raise :class:`MissingExtra` when the guarded import of ``package`` left ``module`` None."""
    if module is None:
        raise MissingExtra(feature, package, extra)
