"""Dihedral augmentation of training images: the group, the per-image draw, its seeding."""

from __future__ import annotations

import itertools

import pytest
import torch

from subslope.nre.augment import N_DIHEDRAL, dihedral, random_dihedral, step_generator


def _image(n=5):
    return torch.arange(float(n * n)).reshape(1, 1, n, n)


def test_eight_distinct_elements_forming_a_group():
    x = _image()
    images = [dihedral(x, k) for k in range(N_DIHEDRAL)]
    assert torch.equal(images[0], x)
    keys = {tuple(im.flatten().tolist()) for im in images}
    assert len(keys) == N_DIHEDRAL
    # closed under composition, and every element has an inverse
    for a, b in itertools.product(range(N_DIHEDRAL), repeat=2):
        assert tuple(dihedral(dihedral(x, a), b).flatten().tolist()) in keys
    for a in range(N_DIHEDRAL):
        assert any(torch.equal(dihedral(dihedral(x, a), b), x) for b in range(N_DIHEDRAL))


def test_pixel_grid_maps_onto_itself():
    """A point source at (x, y) on the symmetric grid goes to a grid point at the rotated
    or reflected position: rotation by 90° sends (x, y) to (−y, x)."""
    n = 7
    img = torch.zeros(n, n)
    j, i = 1, 5  # image[j, i] at (x_i, y_j); centre index 3
    img[j, i] = 1.0
    rot = dihedral(img, 1)
    (jj, ii) = (rot == 1).nonzero()[0].tolist()
    x, y = i - 3, j - 3
    # torch.rot90 on (row, col) = (y, x) axes turns the array counter-clockwise
    assert (ii - 3, jj - 3) in {(-y, x), (y, -x)}
    assert abs(ii - 3) ** 2 + abs(jj - 3) ** 2 == x * x + y * y


def test_random_draw_per_image_keeps_pixels_and_is_seeded():
    x = torch.randn(200, 1, 6, 6, dtype=torch.float64)
    a = random_dihedral(x, step_generator(7, 11))
    b = random_dihedral(x, step_generator(7, 11))
    c = random_dihedral(x, step_generator(7, 12))
    assert torch.equal(a, b) and not torch.equal(a, c)
    # each image is one of its own eight transforms: same sorted pixels
    assert torch.equal(a.flatten(1).sort(1).values, x.flatten(1).sort(1).values)
    used = set()
    for row in range(x.shape[0]):
        ks = [k for k in range(N_DIHEDRAL) if torch.equal(dihedral(x[row], k), a[row])]
        assert ks
        used.update(ks)
    assert used == set(range(N_DIHEDRAL))


def test_bad_input():
    with pytest.raises(ValueError, match="0..7"):
        dihedral(_image(), 8)
    with pytest.raises(ValueError, match="square"):
        dihedral(torch.zeros(1, 4, 5), 1)
