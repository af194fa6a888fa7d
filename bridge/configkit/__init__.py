"""The machinery behind :mod:`bridge.config`: rules, declarations, the loader, the docs.

:mod:`bridge.config` declares the daemon's sections with :func:`~bridge.configkit.schema.setting`;
everything generic lives here, knows nothing of those sections and imports nothing of
the bridge but :mod:`bridge.files` (the safe file reader):

* :mod:`~bridge.configkit.rules` -- value rules (ranges, choices, endpoint and path shapes)
* :mod:`~bridge.configkit.schema` -- ``setting()``, sections, :class:`ConfigError`
* :mod:`~bridge.configkit.loader` -- TOML file + overrides -> validated dataclasses, and back
* :mod:`~bridge.configkit.docs` -- the configuration reference, generated from the declarations
"""
