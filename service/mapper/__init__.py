"""Incremental 3D Gaussian Splatting training: the mapper of a map session
(:class:`~.mapper.Mapper`), its densification (:mod:`.densify`), its topology changes
(:mod:`.topology`) and Gaussians from points and depth (:mod:`.points`). The settings are
:class:`~agilegs.config.mapper.MapperConfig`."""
