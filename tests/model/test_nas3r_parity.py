"""This project's network against NAS3R's own code: a fixture written by benchmarks/nas3r_parity.py from NAS3R's
classes at a reduced size (weights, inputs, outputs), so parity is checked without NAS3R's source."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from aesplat.model.encoder import EncoderConfig
from aesplat.model.model import AESplatModel, ModelConfig
from aesplat.model.nas3r import load_nas3r_state
from aesplat.model.transformer import TransformerConfig
from aesplat.render import render
from aesplat.types import Gaussians

FIXTURE = Path(__file__).parent / "fixtures" / "nas3r_parity.pt"
TOLERANCE = 1e-4  # largest absolute difference over NAS3R's largest absolute value, per output


@pytest.fixture(scope="module")
def fixture() -> dict:
    return torch.load(FIXTURE, map_location="cpu", weights_only=True)


def model_for(fixture: dict, network: str, camera_mask: bool = False) -> AESplatModel:
    """The fixture's network with NAS3R's weights: ``camera_mask=False`` is NAS3R's camera head exactly."""
    net = {**fixture["net"], "camera_mask": camera_mask}
    transformer = {**net.pop("transformer"), "intrinsics_tokens": network == "nas3r-I"}
    transformer["layers"] = tuple(transformer["layers"])
    cfg = ModelConfig(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in net.items() if k != "encoder"},
        encoder=EncoderConfig(**net["encoder"]),
        transformer=TransformerConfig(**transformer),
    )
    model = AESplatModel(cfg)
    state = {"encoder." + k: v for k, v in fixture["states"][network].items()}
    load_nas3r_state(model, state, FIXTURE)
    return model.eval()


def run(model: AESplatModel, inputs: dict, targets: bool = True) -> dict:
    vc = int(inputs["vc"])
    images = inputs["images"] if targets else inputs["images"][:, :vc]
    k = inputs["intrinsics"][:, : images.shape[1]] if model.takes_intrinsics else None
    with torch.no_grad():
        out = model(images[:, :vc], images[:, vc:] if targets else None, intrinsics=k)
    g = out.gaussians
    return {"extrinsics": out.extrinsics, "intrinsics": out.intrinsics, "depth": out.depth, "means": g.means,
            "scales": g.scales, "quats": g.quats, "opacities": g.opacities, "sh": g.sh}  # fmt: skip


def relative(ours: torch.Tensor, theirs: torch.Tensor) -> float:
    return float((ours.double() - theirs.double()).abs().max() / theirs.double().abs().max())


@pytest.mark.parametrize("case", ["2+1", "3+1", "2+1-I"])
def test_every_output_matches_nas3r(fixture: dict, case: str) -> None:
    entry = next(c for c in fixture["cases"] if c["case"] == case)["fixture"]
    ours = run(model_for(fixture, entry["network"]), entry["inputs"])
    theirs = entry["outputs"]
    assert set(theirs) == set(ours)
    for name, ref in theirs.items():
        assert ours[name].shape == ref.shape, name
        assert relative(ours[name], ref) <= TOLERANCE, (name, relative(ours[name], ref))
    # the outputs are not trivial: cameras move, depths spread, the SH beyond degree 0 are not zero
    assert theirs["extrinsics"][:, 1:, :3, 3].abs().max() > 1e-3
    assert theirs["depth"].std() > 0.1 and theirs["sh"][..., 1:, :].abs().max() > 1e-4
    vc = int(entry["inputs"]["vc"])
    size = entry["inputs"]["images"].shape[-2:]
    cams = theirs["extrinsics"][:, vc:], theirs["intrinsics"][:, vc:]

    def draw(o: dict) -> torch.Tensor:
        g = Gaussians(
            means=o["means"], quats=o["quats"], scales=o["scales"], opacities=o["opacities"], sh=o["sh"]
        )
        return render(g, *cams, *size, backend="torch").color

    mse = float(((draw(ours) - draw(theirs)) ** 2).mean())
    assert mse == 0 or -10 * torch.log10(torch.tensor(mse)) >= 60


@pytest.mark.parametrize("case", ["2+1", "2+1-I"])
def test_the_masked_camera_head_keeps_the_targets_out_of_the_context(fixture: dict, case: str) -> None:
    """The default camera head (camera_mask): with the target views given, the context cameras, depth and
    Gaussians are NAS3R's on the context views alone; NAS3R's own head lets the targets move them."""
    entry = next(c for c in fixture["cases"] if c["case"] == case)["fixture"]
    vc = int(entry["inputs"]["vc"])
    masked = run(model_for(fixture, entry["network"], camera_mask=True), entry["inputs"])
    alone = entry["context_outputs"]
    for name, ref in alone.items():
        ours = masked[name][:, :vc] if name in ("extrinsics", "intrinsics") else masked[name]
        assert relative(ours, ref) <= TOLERANCE, name
    without = run(model_for(fixture, entry["network"], camera_mask=True), entry["inputs"], targets=False)
    assert relative(masked["means"], without["means"]) <= TOLERANCE


def test_nas3r_camera_head_lets_the_targets_move_the_context() -> None:
    """Why the mask is the default: in NAS3R's own outputs (fixture), the context Gaussians and cameras with a
    target view differ from those of the context alone."""
    entry = next(c for c in torch.load(FIXTURE, weights_only=True)["cases"] if c["case"] == "2+1")["fixture"]
    with_target, alone = entry["outputs"], entry["context_outputs"]
    assert relative(with_target["means"], alone["means"]) > 1e-3
    assert relative(with_target["extrinsics"][:, :2], alone["extrinsics"]) > 1e-3


def test_the_intrinsics_network_keeps_the_given_intrinsics_beside_given_poses(fixture: dict) -> None:
    """-I with the data set's cameras (posed training): the camera head's prediction, which a pose loss
    supervises, carries the intrinsics the network was given, as the rendering cameras do."""
    entry = next(c for c in fixture["cases"] if c["case"] == "2+1-I")["fixture"]
    model = model_for(fixture, "nas3r-I", camera_mask=True)
    inputs = entry["inputs"]
    vc, k = int(inputs["vc"]), inputs["intrinsics"]
    poses = torch.eye(4).expand(*k.shape[:2], 4, 4)
    with torch.no_grad():
        out = model(inputs["images"][:, :vc], inputs["images"][:, vc:], extrinsics=poses, intrinsics=k)
    assert torch.equal(out.predicted_cameras[1], k) and torch.equal(out.intrinsics, k)
    assert out.predicted_cameras[0].shape == poses.shape


def test_the_intrinsics_network_reads_the_intrinsics(fixture: dict) -> None:
    """-I: other intrinsics change the cameras and Gaussians (the K-token is where the camera head reads)."""
    entry = next(c for c in fixture["cases"] if c["case"] == "2+1-I")["fixture"]
    model = model_for(fixture, "nas3r-I")
    inputs = dict(entry["inputs"])
    base = run(model, inputs)
    inputs["intrinsics"] = inputs["intrinsics"] * torch.tensor([1.3, 1.3, 1.0])[:, None]
    moved = run(model, inputs)
    assert relative(moved["extrinsics"], base["extrinsics"]) > 1e-3
    assert torch.equal(moved["intrinsics"], inputs["intrinsics"])  # -I takes the intrinsics it is given
