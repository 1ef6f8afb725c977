"""How to install an optional extra (``plot``, ``colmap``) of the project: from its checkout,
since hmcc-match is not on a package index."""

from __future__ import annotations

from pathlib import Path

__all__ = ["install_hint"]

#: The checkout this package runs from, when it runs from one (an editable install:
#: ``service/hmcc_cli/`` two folders below the root).
_CHECKOUT = Path(__file__).resolve().parents[2]


def install_hint(extra: str) -> str:
    """The command that installs ``extra``: the checkout's ``scripts/bootstrap EXTRA`` (into its
    ``.venv``, which ``scripts/hmcc`` runs), or pip on the checkout; named from the working
    folder when it is the checkout, else by absolute paths."""
    bootstrap = _CHECKOUT / "scripts" / "bootstrap"
    here = f"run scripts/bootstrap {extra} (or pip install '.[{extra}]')"
    if not bootstrap.is_file():  # installed from a copy of the checkout (a wheel, an image)
        return f"in the project's checkout, {here}"
    if Path.cwd().resolve() == _CHECKOUT:
        return here
    return f"run {bootstrap} {extra} (or pip install '{_CHECKOUT}[{extra}]')"
