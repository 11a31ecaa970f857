"""The service's settings as a user meets them: a data dir that cannot be one, a token file
left readable by others."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from services.config.settings import ServiceSettings, SettingsError
from services.runtime.runtime import Runtime


def test_a_data_dir_that_is_a_file_is_named_in_one_sentence(tmp_path: Path) -> None:
    """It was "[Errno 17] File exists"."""
    where = tmp_path / "data"
    where.write_text("not a directory\n")
    settings = ServiceSettings(data_dir=where)
    with pytest.raises(SettingsError, match=rf"SWPC_DATA_DIR={where}: not a directory"):
        Runtime(settings)
    with pytest.raises(SettingsError, match=r"SWPC_DATA_DIR=.*not a directory"):
        settings.ensure_token()  # the generated token's file is in it too
    assert where.read_text() == "not a directory\n"


def test_a_token_file_readable_by_others_is_tightened_to_0600(tmp_path: Path) -> None:
    """An existing api-token at 0644 was kept at 0644."""
    settings = ServiceSettings(data_dir=tmp_path)
    token = settings.ensure_token()
    path = settings.token_file
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    path.chmod(0o644)
    again = ServiceSettings(data_dir=tmp_path)
    assert again.ensure_token() == token
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
