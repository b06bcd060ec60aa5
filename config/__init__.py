"""agilegs.config: the typed settings of the maths and the mapper, and the tolerances of the
geometry conventions.

Neither wire nor maths: it depends on pydantic only, and both the maths
(:mod:`agilegs.service.nbv`, :mod:`agilegs.service.mapper`) and the wire contract
(:mod:`agilegs.schemas`, whose :mod:`agilegs.schemas.config` turns each settings class into the
patch a request carries) import it. :mod:`.selection` holds :class:`SelectConfig` and its
parts, :mod:`.mapper` :class:`MapperConfig`, :mod:`.types` the constrained scalars and
:func:`validate_config`, :mod:`.geometry` the pose tolerances.
"""
