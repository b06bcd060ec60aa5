"""Incremental 3D Gaussian Splatting training: the mapper of a map session
(:class:`~.mapper.Mapper`), its densification (:mod:`.densify`), its topology changes
(:mod:`.topology`) and Gaussians from points and depth (:mod:`.points`). The settings are
:class:`~agilegs.config.mapper.MapperConfig`."""

from agilegs.config.mapper import MapperConfig

from .densify import Densification, plan_densification
from .mapper import Mapper
from .points import backproject_depth, nearest_neighbour_scales
from .topology import TopologyChange, remap_per_gaussian

__all__ = [
    "Densification",
    "Mapper",
    "MapperConfig",
    "TopologyChange",
    "backproject_depth",
    "nearest_neighbour_scales",
    "plan_densification",
    "remap_per_gaussian",
]
