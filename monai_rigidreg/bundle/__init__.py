"""The shipped MONAI bundle (``bundles/cbct_ct_rigid``, installed as ``monai_rigidreg._bundles``).

- :mod:`~monai_rigidreg.bundle.loader`: where the bundle is, its network loaded with the settings its
  ``inference.json`` declares.
- :mod:`~monai_rigidreg.bundle.config`: the plain reader of its JSON configs (no MONAI on the ``register`` path).
- :mod:`~monai_rigidreg.bundle.entry_points`: what the bundle's configs call (``bundle_check_inputs``, ``bundle_run``,
  ``bundle_evaluate``): errors end ``python -m monai.bundle run`` with one line and the command line's exit status.
"""

from monai_rigidreg.core.lazy_exports import lazy_exports

_LOADER = "monai_rigidreg.bundle.loader"
_NAMES = {name: _LOADER for name in ("DEFAULT_BUNDLE_NAME", "default_bundle_path", "load_bundle_network",
                                     "bundle_settings", "refuse_package_folders")}
__all__ = list(_NAMES)
__getattr__, __dir__ = lazy_exports(__name__, {**_NAMES, "SETTING_KEYS": _LOADER, "PACKAGE_DIR": _LOADER})
