import pytest
import torch

from aesplat.types import BatchedExample, BatchedViews, Gaussians, RenderOutput


def gaussians(b=2, n=5, k=4):
    return dict(
        means=torch.zeros(b, n, 3),
        quats=torch.zeros(b, n, 4),
        scales=torch.ones(b, n, 3),
        opacities=torch.ones(b, n),
        sh=torch.zeros(b, n, k, 3),
    )


def views(b=2, v=2, h=8, w=8):
    return dict(
        images=torch.rand(b, v, 3, h, w),
        extrinsics=torch.eye(4).expand(b, v, 4, 4),
        intrinsics=torch.eye(3).expand(b, v, 3, 3),
        index=torch.zeros(b, v, dtype=torch.long),
    )


def test_valid_containers_build():
    g = Gaussians(**gaussians())
    assert (g.batch_size, g.num_gaussians, g.sh_degree) == (2, 5, 1)
    v = BatchedViews(**views())
    assert v.num_views == 2 and v.image_shape == (8, 8)
    ex = BatchedExample(context=v, target=BatchedViews(**views(v=1)), scene=["a", "b"])
    assert ex.to(dtype=torch.float64).context.index.dtype == torch.long
    RenderOutput(
        color=torch.zeros(1, 2, 3, 4, 4), depth=torch.zeros(1, 2, 1, 4, 4), alpha=torch.zeros(1, 2, 1, 4, 4)
    )


@pytest.mark.parametrize(
    "field,value,message",
    [
        ("means", torch.zeros(2, 5, 2), "Gaussians.means must end in \\[3\\]"),
        ("quats", torch.zeros(2, 5, 3), "Gaussians.quats must end in \\[4\\]"),
        ("opacities", torch.zeros(2, 5, 1), "Gaussians.opacities must have 2 dimensions"),
        ("sh", torch.zeros(2, 5, 5, 3), "K=5"),
        ("scales", torch.zeros(2, 4, 3), "leading dimensions disagree"),
        ("means", torch.zeros(2, 5, 3, dtype=torch.long), "floating-point"),
        ("sh", [0.0], "must be a torch.Tensor"),
    ],
)
def test_gaussians_reject_wrong_shapes(field, value, message):
    kw = gaussians()
    kw[field] = value
    with pytest.raises((ValueError, TypeError), match=message):
        Gaussians(**kw)


def test_views_and_examples_reject_wrong_shapes():
    kw = views()
    kw["extrinsics"] = torch.eye(3).expand(2, 2, 3, 3)
    with pytest.raises(ValueError, match="BatchedViews.extrinsics must end in \\[4, 4\\]"):
        BatchedViews(**kw)
    kw = views()
    kw["index"] = torch.zeros(2, 2)
    with pytest.raises(TypeError, match="index must be an integer"):
        BatchedViews(**kw)
    with pytest.raises(ValueError, match="image sizes differ"):
        BatchedExample(context=BatchedViews(**views()), target=BatchedViews(**views(h=4)))


def test_uint8_images_convert_to_unit_floats():
    kw = views()
    kw["images"] = torch.full((2, 2, 3, 8, 8), 255, dtype=torch.uint8)
    v = BatchedViews(**kw)
    ex = BatchedExample(context=v, target=v).float_images()
    assert ex.context.images.dtype == torch.float32 and torch.equal(ex.target.images, torch.ones(2, 2, 3, 8, 8))


def test_example_highlight_mask_is_checked_and_moves_with_the_batch():
    ctx, tgt = BatchedViews(**views()), BatchedViews(**views(v=3))
    mask = torch.rand(2, 3, 1, 8, 8) > 0.5
    ex = BatchedExample(context=ctx, target=tgt, highlight=mask)
    assert torch.equal(ex.to(dtype=torch.float64).highlight, mask)  # a mask stays a mask
    assert BatchedExample(context=ctx, target=tgt).highlight is None
    with pytest.raises(ValueError, match="highlight must have shape \\(2, 3, 1, 8, 8\\)"):
        BatchedExample(context=ctx, target=tgt, highlight=mask[:, :2])
    with pytest.raises(TypeError, match="bool"):
        BatchedExample(context=ctx, target=tgt, highlight=mask.float())
