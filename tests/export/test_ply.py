import numpy as np
import pytest
import torch

from aesplat.export import (
    drop_transparent,
    gaussians_to_ply_array,
    keep_most_opaque,
    ply_property_names,
    write_ply,
)
from aesplat.geometry import num_sh_coeffs
from aesplat.types import Gaussians


def read_ply(path) -> dict[str, np.ndarray]:
    """A minimal binary-little-endian PLY reader written independently of the writer: property -> [N]."""
    data = open(path, "rb").read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    count = int(next(line for line in lines if line.startswith("element vertex")).split()[-1])
    names = [line.split()[2] for line in lines if line.startswith("property")]
    assert all(line.split()[1] == "float" for line in lines if line.startswith("property"))
    table = np.frombuffer(data[end:], dtype="<f4").reshape(count, len(names))
    return {name: table[:, i] for i, name in enumerate(names)}


def random_gaussians(b: int = 2, n: int = 50, degree: int = 4) -> Gaussians:
    k = num_sh_coeffs(degree)
    return Gaussians(
        means=torch.randn(b, n, 3),
        quats=torch.randn(b, n, 4),
        scales=torch.rand(b, n, 3) * 0.1 + 1e-3,
        opacities=torch.rand(b, n) * 0.98 + 0.01,
        sh=torch.randn(b, n, k, 3),
    )


def test_property_order_is_the_reference_layout():
    names = ply_property_names(3)
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert len(ply_property_names(0)) == 17 and len(ply_property_names(4)) == 17 + 72


@pytest.mark.parametrize("degree", [0, 2, 4])
def test_round_trip_recovers_every_parameter(tmp_path, degree):
    g = random_gaussians(degree=degree)
    path = write_ply(tmp_path / "out" / "g.ply", g, index=1)
    ply = read_ply(path)
    n, k = g.num_gaussians, num_sh_coeffs(degree)
    assert set(ply) == set(ply_property_names(degree))
    means = np.stack([ply["x"], ply["y"], ply["z"]], -1)
    np.testing.assert_allclose(means, g.means[1].numpy(), rtol=1e-6)
    assert not any(ply[c].any() for c in ("nx", "ny", "nz"))
    # Loaded the way the reference 3DGS loads it: sigmoid, exp, normalise, channel-major f_rest.
    np.testing.assert_allclose(1 / (1 + np.exp(-ply["opacity"])), g.opacities[1].numpy(), rtol=1e-5)
    scales = np.exp(np.stack([ply[f"scale_{i}"] for i in range(3)], -1))
    np.testing.assert_allclose(scales, g.scales[1].numpy(), rtol=1e-5)
    quats = np.stack([ply[f"rot_{i}"] for i in range(4)], -1)
    want = g.quats[1] / g.quats[1].norm(dim=-1, keepdim=True)
    np.testing.assert_allclose(quats, want.numpy(), rtol=1e-5, atol=1e-6)
    dc = np.stack([ply[f"f_dc_{i}"] for i in range(3)], -1)
    rest = np.zeros((n, 0)) if k == 1 else np.stack([ply[f"f_rest_{i}"] for i in range(3 * (k - 1))], -1)
    rest = rest.reshape(n, 3, k - 1)
    sh = np.concatenate([dc[:, None], rest.transpose(0, 2, 1)], axis=1)
    np.testing.assert_allclose(sh, g.sh[1].numpy(), rtol=1e-6)


def test_f_rest_is_channel_major():
    g = random_gaussians(b=1, n=1, degree=3)
    sh = torch.zeros_like(g.sh)
    sh[0, 0, 1, 0] = 1.0  # red, first higher-order coefficient -> f_rest_0
    sh[0, 0, 1, 1] = 2.0  # green, first higher-order coefficient -> f_rest_15
    sh[0, 0, 15, 2] = 3.0  # blue, last coefficient -> f_rest_44
    g = Gaussians(g.means, g.quats, g.scales, g.opacities, sh)
    row = gaussians_to_ply_array(g)[0]
    rest = dict(zip(ply_property_names(3), row))
    assert rest["f_rest_0"] == 1.0 and rest["f_rest_15"] == 2.0 and rest["f_rest_44"] == 3.0
    assert sum(v != 0 for name, v in rest.items() if name.startswith("f_rest")) == 3


def test_truncated_degree_keeps_the_low_bands(tmp_path):
    g = random_gaussians(b=1, degree=4)
    ply = read_ply(write_ply(tmp_path / "g.ply", g, sh_degree=1))
    assert sum(name.startswith("f_rest") for name in ply) == 9
    np.testing.assert_allclose(ply["f_rest_3"], g.sh[0, :, 1, 1].numpy())  # green, coefficient 1
    with pytest.raises(ValueError, match="carry degree 1"):
        write_ply(tmp_path / "h.ply", random_gaussians(degree=1), sh_degree=2)


def test_degenerate_values_stay_finite(tmp_path):
    g = random_gaussians(b=1, n=4, degree=1)
    g = Gaussians(
        g.means,
        torch.zeros_like(g.quats),
        torch.zeros_like(g.scales),
        torch.tensor([[0.0, 1.0, 0.5, 1e-9]]),
        g.sh,
    )
    ply = read_ply(write_ply(tmp_path / "g.ply", g))
    assert all(np.isfinite(v).all() for v in ply.values())
    np.testing.assert_array_equal(ply["rot_0"], 1.0)  # a zero quaternion is written as the identity
    assert ply["opacity"][0] < -10 and ply["opacity"][1] > 10


def test_keep_most_opaque_keeps_the_highest_opacities():
    g = random_gaussians(b=2, n=40, degree=1)
    kept = keep_most_opaque(g, 0.25)
    assert kept.num_gaussians == 10
    for b in range(2):
        want = g.opacities[b].sort(descending=True).values[:10]
        torch.testing.assert_close(kept.opacities[b].sort(descending=True).values, want)
        # Every field follows the same selection.
        rows = [int((g.opacities[b] == o).nonzero()) for o in kept.opacities[b]]
        torch.testing.assert_close(kept.means[b], g.means[b, rows])
        torch.testing.assert_close(kept.sh[b], g.sh[b, rows])
    assert keep_most_opaque(g, 1.0) is g
    with pytest.raises(ValueError, match="fraction"):
        keep_most_opaque(g, 0.0)


def test_drop_transparent():
    g = random_gaussians(b=1, n=100, degree=0)
    kept = drop_transparent(g, 0.5)
    assert kept.num_gaussians == int((g.opacities >= 0.5).sum())
    assert bool((kept.opacities >= 0.5).all())
    assert drop_transparent(g, 2.0).num_gaussians == 1  # never empty
    assert drop_transparent(g, 0.0) is g  # no threshold: every Gaussian, as given
    with pytest.raises(ValueError, match="one scene"):
        drop_transparent(random_gaussians(b=2), 0.1)
