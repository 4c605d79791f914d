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
- ``archive_bounds``: .npz archives from untrusted bytes, every size decided before anything is inflated
  (record uploads, NPZ bodies, stream tokens).

Dependency rule (import contracts in pyproject.toml; docs/architecture.md): storage imports the method, never
the other way round; ``operations``, ``training``, ``service`` and ``cli`` import both.
"""
