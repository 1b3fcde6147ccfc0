"""The emission kinds' plain table (:mod:`pyro_slam.slam.kinds`), which the configuration
checks without loading the networks."""

from __future__ import annotations

from pyro_slam.slam import kinds
from pyro_slam.slam.components import EMISSIONS, EmissionKind


def test_the_shipped_kinds_have_the_traits_the_configuration_checks():
    """The configuration's plain table of the shipped kinds (:mod:`pyro_slam.slam.kinds`) says
    what their registered :class:`EmissionKind` says, in the one registry."""
    assert EMISSIONS is kinds.EMISSIONS
    for traits in kinds.BUILTIN:
        kind = EMISSIONS[traits.name]
        assert isinstance(kind, EmissionKind), traits.name
        assert (kind.observation, kind.rays) == (traits.observation, traits.rays), traits.name
