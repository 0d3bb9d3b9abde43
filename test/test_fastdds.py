"""The Fast DDS large-message profile: found in the source tree or an ament install, set only when none is set."""
from __future__ import annotations

from pathlib import Path

import pytest

from gd_completion import fastdds

REPO = Path(__file__).resolve().parents[1]


def test_source_tree_profile_is_set_when_none_is() -> None:
    environ: dict[str, str] = {}
    profile = REPO / "config" / "fastdds_large_messages.xml"
    assert fastdds.use_large_message_profile(environ) == str(profile)
    assert environ == {"FASTRTPS_DEFAULT_PROFILES_FILE": str(profile)}
    assert "<transport_id>shm_large</transport_id>" in profile.read_text()


@pytest.mark.parametrize("variable", fastdds.PROFILE_VARIABLES)
def test_a_profile_set_by_the_user_is_kept(variable: str) -> None:
    environ = {variable: "/etc/my_profile.xml"}
    assert fastdds.use_large_message_profile(environ) == "/etc/my_profile.xml"
    assert environ == {variable: "/etc/my_profile.xml"}


def test_installed_profile_through_ament_index(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Outside the source tree the profile comes from share/gd_completion/config of the ament prefix (the layout
    setup.py installs), found through ament_index_python; without either, nothing is set."""
    pytest.importorskip("ament_index_python")
    monkeypatch.setattr(fastdds, "SOURCE_CONFIG", tmp_path / "no_source_tree")
    monkeypatch.setattr(fastdds.sys, "prefix", str(tmp_path / "no_prefix"))
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "install"))
    environ: dict[str, str] = {}
    assert fastdds.use_large_message_profile(environ) is None and environ == {}

    share = tmp_path / "install" / "share"
    (share / "ament_index" / "resource_index" / "packages").mkdir(parents=True)
    (share / "ament_index" / "resource_index" / "packages" / "gd_completion").touch()
    (share / "gd_completion" / "config").mkdir(parents=True)
    installed = share / "gd_completion" / "config" / "fastdds_large_messages.xml"
    installed.write_bytes((REPO / "config" / "fastdds_large_messages.xml").read_bytes())
    assert fastdds.use_large_message_profile(environ) == str(installed)
    assert environ == {"FASTRTPS_DEFAULT_PROFILES_FILE": str(installed)}
