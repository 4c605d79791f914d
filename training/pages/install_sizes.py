"""docs/deploy.md's install sizes ("Install tiers"), a block of that page rendered from the stored run of
tools/install_sizes.py (docs/runs/install/sizes.json): ``python tools/install_sizes.py --render docs/deploy.md``."""
from __future__ import annotations

from gpnarx.training.pages.markdown import row, rule

BEGIN = "<!-- install-sizes: rendered by tools/install_sizes.py from docs/runs/install/sizes.json -->"
END = "<!-- /install-sizes -->"


def _mb(n: int) -> str:
    return f"{n / 1e6:.0f} MB"


def render(run: dict) -> str:
    """The block of docs/deploy.md: the tiers' sizes and packages, from a stored run."""
    t = run["tiers"]
    core, train, image = t["core"], t["train"], t["image"]
    lines = [BEGIN, "",
             f"Installed from `requirements.lock` ({run['lock_pins']} pins with hashes; the wheels "
             f"{_mb(run['wheels_bytes'])}) into fresh venvs, offline, by `tools/install_sizes.py` (Python "
             f"{run['python']}, {run['machine']}); sizes are the bytes of the files each adds to an empty venv's "
             "site-packages, byte-compiled files included. Stored run: `docs/runs/install/sizes.json`.", "",
             row(["install", "packages", "site-packages", "of which `__pycache__`", "largest"]), rule(5)]
    for label, tier in (("core: `gpnarx`", core), ("core before the tiers: `gpnarx[train]`", train),
                        (f"the image: `{image['spec']}`", image)):
        lines.append(row([label, str(tier["n_packages"]), _mb(tier["site_packages_bytes"]), _mb(tier["pycache_bytes"]),
                          ", ".join(f"{k} {_mb(v)}" for k, v in tier["largest"][:4])]))
    only_train = sorted(set(train["packages"]) - set(core["packages"]))
    only_image = sorted(set(image["packages"]) - set(train["packages"]))
    lines += ["",
              f"The core's packages: {', '.join(f'{k} {v}' for k, v in core['packages'].items())}.", "",
              f"`train` adds {len(only_train)}: {', '.join(only_train)} "
              f"({_mb(train['site_packages_bytes'] - core['site_packages_bytes'])}); the image's extras add "
              f"{len(only_image)} more: {', '.join(only_image)}.", "",
              f"The image's Python layer is thus about {_mb(image['site_packages_bytes'])} on top of its base image "
              f"`{run['base_image']}`, before the default registry that `gpnarx build-defaults` writes at image "
              "build.", "", END]
    return "\n".join(lines)
