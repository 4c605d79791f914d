"""Storage: the method's objects as files and objects, apart from the method (``gpnarx.model``).

- ``bundle``: the bundle file format (manifest, schema migrations, checksums, atomic publication,
  verified loading); the fitted model's values themselves are the estimator's
  (``GPNARX.fitted_description`` / ``fitted_arrays`` / ``from_fitted``).
- ``registry``: versioned bundles by name, aliases, lazy loading and rescans.
- ``remote``: where a registry lives: a local folder, or objects behind an fsspec URL, and their cache.
- ``atomicio``: atomic local file writes.
- ``record_formats`` (and ``record_formats_lab``, extra ``formats``): record file contents parsed into a
  ``model.record.Record``; ``record_files``: record files and LMS folders read and written.
- ``jsonsafe``: JSON encoding of numpy values (manifests, CLI output, HTTP bodies).

Dependency rule (import contracts in pyproject.toml): storage imports the method, never the other way
round; ``training``, ``service`` and ``cli`` import both. The free run's stream token
(``model.stream_token``) stays with the method: it is a free-run state in portable form, no file or
network I/O, and the framework-free operations in ``model`` use it.
"""
