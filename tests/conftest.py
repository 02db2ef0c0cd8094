"""Shared fixtures: the shipped body and a short real clip, loaded once per session."""

from __future__ import annotations

import pytest

from smln.geometry import set_threads

set_threads(2)


@pytest.fixture(scope="session")
def body():
    from smln.body import load_body

    return load_body("female_average")


@pytest.fixture(scope="session")
def walk_sequence(body):
    from smln.motion import load_body_sequence

    return load_body_sequence("02_01_walk", body)
