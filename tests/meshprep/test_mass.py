"""meshprep.mass: exact polyhedral mass properties against the analytic formulas."""

from __future__ import annotations

import numpy as np
import pytest

from meshprep.constants import MASS_PROPERTIES_REL_TOL as TOL
from meshprep.creation import box, cylinder, sphere, torus
from meshprep.mass import mass_properties, signed_volume

RHO = 850.0


def _check(v, f, volume, diag_inertia_per_mass):
    mp = mass_properties(v, f, density=RHO)
    assert mp.volume == pytest.approx(volume, rel=TOL)
    assert mp.mass == pytest.approx(RHO * volume, rel=TOL)
    scale = float(np.abs(v).max())
    assert np.allclose(mp.com, 0.0, atol=1e-9 * scale)
    expect = np.diag(diag_inertia_per_mass) * RHO * volume
    assert np.allclose(np.diag(mp.inertia), np.diag(expect), rtol=TOL)
    off = mp.inertia - np.diag(np.diag(mp.inertia))
    assert np.abs(off).max() <= 1e-9 * np.abs(expect).max()


def test_box():
    a, b, c = 1.0, 2.0, 3.0
    v, f = box((a, b, c))
    _check(v, f, a * b * c, np.array([b * b + c * c, a * a + c * c, a * a + b * b]) / 12)


def test_sphere():
    r = 2.0
    v, f = sphere(r)
    _check(v, f, 4 / 3 * np.pi * r ** 3, np.full(3, 0.4 * r * r))


def test_cylinder():
    r, h = 0.5, 2.0
    v, f = cylinder(r, h)
    side = (3 * r * r + h * h) / 12
    _check(v, f, np.pi * r * r * h, np.array([side, side, 0.5 * r * r]))


def test_torus():
    R, r = 1.0, 0.25
    v, f = torus(R, r)
    axial = R * R + 0.75 * r * r
    side = 0.5 * R * R + 0.625 * r * r
    _check(v, f, 2 * np.pi ** 2 * R * r * r, np.array([side, side, axial]))


def test_far_from_origin_translates_com_only():
    v, f = torus(1.0, 0.25, major_segments=64, minor_segments=32)
    near = mass_properties(v, f)
    shift = np.array([1e6, -2e6, 3e6])
    far = mass_properties(v + shift, f)
    assert far.volume == pytest.approx(near.volume, rel=1e-9)
    assert np.allclose(far.com, near.com + shift, atol=1e-6)
    assert np.allclose(far.inertia, near.inertia, rtol=1e-7, atol=1e-9)


def test_rotated_box_inertia_is_rotated():
    v, f = box((1.0, 2.0, 3.0))
    th = 0.3
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    a = mass_properties(v, f).inertia
    b = mass_properties(v @ R.T, f).inertia
    assert np.allclose(b, R @ a @ R.T, atol=1e-12)


def test_inside_out_gives_negative_volume_and_empty_gives_zero():
    v, f = box()
    assert signed_volume(v, f[:, ::-1]) == pytest.approx(-1.0)
    empty = mass_properties(v, np.zeros((0, 3), dtype=np.int32))
    assert empty.volume == 0.0 and empty.mass == 0.0
