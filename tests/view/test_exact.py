"""The exact render mode draws what ``aesplat predict`` draws: the same pixels, to float tolerance, for the same
camera, at SH degree 0 and at the model's degree; and the two degrees differ on this view-dependent scene."""

import numpy as np
import pytest
import torch
from PIL import Image

from aesplat.checkpoint import load_checkpoint
from aesplat.images import load_image, to_uint8
from aesplat.inference import predict_scene, render_views
from aesplat.view.camera import viewpoint_of
from aesplat.view.exact import render_viewpoint
from aesplat.view.scene import scene_from_checkpoint, scene_from_path
from tests.helpers import IMAGE_SIZE, SH_DEGREE
from tests.prediction_helpers import make_prediction

pytestmark = pytest.mark.filterwarnings("ignore:LPIPS metric unavailable")


@pytest.fixture(scope="module")
def predicted(tmp_path_factory):
    """The prediction folder, and predict's own renders of its input cameras at each SH degree."""
    folder, ckpt, images = make_prediction(tmp_path_factory.mktemp("view"))
    loaded = load_checkpoint(ckpt)
    pixels = torch.stack([load_image(p, IMAGE_SIZE).image for p in images])
    pred = predict_scene(loaded.model, pixels)
    options = loaded.render_options()
    cameras = (pred.gaussians, pred.extrinsics, pred.intrinsics, IMAGE_SIZE, IMAGE_SIZE)
    expected = {degree: render_views(*cameras, {**options, "sh_degree": degree}) for degree in (0, SH_DEGREE)}
    return folder, ckpt, images, expected


def exact_renders(scene, degree: int) -> torch.Tensor:
    views = [viewpoint_of(c.extrinsics, c.intrinsics, c.width, c.height) for c in scene.cameras]
    return torch.stack([render_viewpoint(scene, v, IMAGE_SIZE, sh_degree=degree) for v in views])


@pytest.mark.parametrize("degree", [0, SH_DEGREE])
def test_exact_mode_equals_predict_from_the_folder(predicted, degree):
    folder, _, _, expected = predicted
    scene = scene_from_path(folder)
    assert scene.sh_degree == SH_DEGREE and len(scene.cameras) == 2
    # the PLY holds opacities as logits and scales as logs in float32: a Gaussian may move by an ulp
    torch.testing.assert_close(exact_renders(scene, degree), expected[degree].clamp(0, 1), atol=1e-4, rtol=0)


@pytest.mark.parametrize("degree", [0, SH_DEGREE])
def test_exact_mode_equals_predict_from_the_checkpoint(predicted, degree):
    _, ckpt, images, expected = predicted
    scene = scene_from_checkpoint(ckpt, [str(p) for p in images], device="cpu")
    torch.testing.assert_close(exact_renders(scene, degree), expected[degree].clamp(0, 1), atol=1e-5, rtol=0)


def test_exact_mode_matches_the_renders_predict_saved(predicted):
    folder, _, _, _ = predicted
    scene = scene_from_path(folder)
    for cam, image in zip(scene.cameras, exact_renders(scene, SH_DEGREE)):
        saved = np.asarray(Image.open(folder / "renders" / f"{scene.cameras.index(cam):02d}_{cam.name}.png"))
        assert np.abs(to_uint8(image).astype(int) - saved.astype(int)).max() <= 1


def test_exact_mode_matches_predict_on_wide_photos(tmp_path):
    folder, _, _ = make_prediction(tmp_path, width=2 * IMAGE_SIZE)  # the model sees them 28 x 56, uncropped
    scene = scene_from_path(folder)
    assert (scene.cameras[0].height, scene.cameras[0].width) == (IMAGE_SIZE, 2 * IMAGE_SIZE)
    for i, image in enumerate(exact_renders(scene, SH_DEGREE)):
        saved = np.asarray(Image.open(folder / "renders" / f"{i:02d}_{scene.cameras[i].name}.png"))
        assert saved.shape == (IMAGE_SIZE, 2 * IMAGE_SIZE, 3)
        assert np.abs(to_uint8(image).astype(int) - saved.astype(int)).max() <= 1


def test_view_dependent_colour_shows_at_the_models_degree(predicted):
    folder, _, _, expected = predicted
    scene = scene_from_path(folder)
    full, base = exact_renders(scene, SH_DEGREE), exact_renders(scene, 0)
    # far beyond the float tolerance above: the higher bands change colours by hundredths here
    assert (full - base).abs().max() > 0.03
    assert (expected[SH_DEGREE] - expected[0]).abs().max() > 0.03


def test_viewpoint_round_trips_a_predicted_camera(predicted):
    scene = scene_from_path(predicted[0])
    for cam in scene.cameras:
        view = viewpoint_of(cam.extrinsics, cam.intrinsics, cam.width, cam.height)
        torch.testing.assert_close(view.extrinsics(), cam.extrinsics, atol=1e-6, rtol=0)
        torch.testing.assert_close(view.intrinsics(cam.height), cam.intrinsics, atol=1e-6, rtol=0)
    wide = viewpoint_of(scene.cameras[0].extrinsics, scene.cameras[0].intrinsics, 56, 28)
    assert wide.size(28) == (28, 56)
    k = wide.intrinsics(28)
    assert k[0, 0] * 56 == pytest.approx(k[1, 1] * 28)  # square pixels
