"""Which params-file sections address a node: rcl's wildcard rules, and files that address none."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from lenn_ros.config import node_key_matches, unmatched_params_files


@pytest.mark.parametrize(
    ("key", "name", "expected"),
    [
        ("/**", "/identifier", True),
        ("/**", "/robot1/arm/ident3", True),
        ("/**/identifier", "/identifier", True),  # ** stands for no token too
        ("/**/identifier", "/robot1/identifier", True),
        ("/**/identifier", "/robot1/ident3", False),
        ("identifier", "/identifier", True),  # no leading slash: the root namespace
        ("identifier", "/id3/identifier", False),
        ("/id3/identifier", "/id3/identifier", True),
        ("/*/identifier", "/id3/identifier", True),
        ("/*/identifier", "/a/b/identifier", False),
        ("/**/arm/*", "/robot/arm/ident3", True),
    ],
)
def test_node_key_matches_like_rcl(key: str, name: str, expected: bool) -> None:
    assert node_key_matches(key, name) is expected


def test_a_file_with_no_section_for_the_node_is_found(tmp_path: Path) -> None:
    shipped = tmp_path / "example3.yaml"
    shipped.write_text(yaml.safe_dump({"/**/identifier": {"ros__parameters": {"example": 3}}}))
    anything = tmp_path / "any.yaml"
    anything.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"example": 3}}}))
    argv = ["identifier", "--ros-args", "--params-file", str(shipped), "--params-file", str(anything)]
    assert unmatched_params_files(argv, "/identifier") == []
    assert unmatched_params_files(argv, "/id3/ident3") == [(str(shipped), ["/**/identifier"])]
