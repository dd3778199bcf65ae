"""Robot descriptions (URDF) of endoscope holders, found by name.

``urdf_path("ecm")`` gives the packaged da Vinci ECM model; any other value is taken as a path to a URDF.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from lapreco_hil.errors import ConfigError

_PACKAGED = {"ecm": "ecm.urdf"}


def urdf_path(name_or_path: str) -> Path:
    if name_or_path in _PACKAGED:
        return Path(str(resources.files(__name__).joinpath(_PACKAGED[name_or_path])))
    path = Path(name_or_path)
    if not path.is_file():
        raise ConfigError(
            f"robot model '{name_or_path}': no such URDF file and no packaged model of that name "
            f"(packaged: {', '.join(sorted(_PACKAGED))})"
        )
    return path


def packaged_models() -> list[str]:
    return sorted(_PACKAGED)
