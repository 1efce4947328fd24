"""The fast execution's frozen batch norms, run in place at inference, equal torchvision's."""

import copy

import torch
from torchvision.ops import FrozenBatchNorm2d

import taptr
from taptr.model.backbone import ResNetBody, frozen_norm_
from taptr.model.execution import EXECUTIONS


def _resnet(generator: torch.Generator) -> ResNetBody:
    """A ResNet-50 trunk whose frozen norms are not the identity."""
    body = ResNetBody().eval()
    for module in body.modules():
        if isinstance(module, FrozenBatchNorm2d):
            channels = module.weight.shape[0]
            module.weight.copy_(torch.rand(channels, generator=generator) + 0.5)
            module.bias.copy_(torch.randn(channels, generator=generator) * 0.1)
            module.running_mean.copy_(torch.randn(channels, generator=generator) * 0.1)
            module.running_var.copy_(torch.rand(channels, generator=generator) + 0.5)
    return body


def _count_norm_calls(body: ResNetBody) -> list[int]:
    calls = [0]

    def count(*args: object) -> None:
        calls[0] += 1

    for module in body.modules():
        if isinstance(module, FrozenBatchNorm2d):
            module.register_forward_hook(count)
    return calls


def test_frozen_norm_in_place_equals_the_module(generator):
    norm = FrozenBatchNorm2d(5)
    norm.weight.copy_(torch.rand(5, generator=generator) + 0.5)
    norm.running_var.copy_(torch.rand(5, generator=generator))
    norm.running_mean.copy_(torch.randn(5, generator=generator))
    x = torch.randn(2, 5, 3, 4, generator=generator)
    expected = norm(x)
    out = frozen_norm_(norm, x)
    assert out.data_ptr() == x.data_ptr()  # written over its input
    torch.testing.assert_close(out, expected, atol=1e-6, rtol=1e-6)


def test_resnet_with_norms_in_place_equals_the_torchvision_blocks(generator):
    body = _resnet(generator)
    calls = _count_norm_calls(body)
    images = torch.randn(2, 3, 64, 96, generator=generator).contiguous(
        memory_format=torch.channels_last
    )
    with torch.no_grad():
        plain = body(images)
        plain_calls = calls[0]
        in_place = body(images, in_place_norms=True)
    assert plain_calls == 53  # 49 in the blocks, 4 in the downsampling shortcuts
    assert calls[0] == plain_calls  # no module norm ran in place
    assert [m.shape for m in in_place] == [m.shape for m in plain]
    for a, b in zip(in_place, plain, strict=True):  # float rounding, relative to the scale
        torch.testing.assert_close(a, b, atol=1e-5 * float(b.abs().max()), rtol=0)


def test_norms_in_place_are_skipped_when_autograd_records(generator):
    body = _resnet(generator)
    calls = _count_norm_calls(body)
    images = torch.randn(1, 3, 32, 32, generator=generator, requires_grad=True)
    levels = body(images, in_place_norms=True)
    assert calls[0] == 53
    levels[-1].sum().backward()
    assert images.grad is not None and images.grad.abs().sum() > 0


def test_the_model_hands_the_flag_to_the_backbone(generator):
    seen = []
    model = taptr.build_model("tiny").eval()
    model.backbone.register_forward_pre_hook(lambda module, inputs: seen.append(inputs[1]))
    images = torch.rand(1, 3, 64, 64, generator=generator)
    with torch.no_grad():
        model.set_execution("fast").encode_images(images)
        model.set_execution("reference").encode_images(images)
    assert seen == [True, False]
    assert [e.in_place_norms for e in EXECUTIONS.values()] == [False, True, False]


def test_folded_norms_give_the_same_maps_in_both_executions(generator):
    for kind in ("resnet50", "resnet18"):
        body = _resnet(generator) if kind == "resnet50" else ResNetBody(kind).eval()
        images = torch.randn(2, 3, 64, 96, generator=generator)
        with torch.no_grad():
            expected = body(images)
            body.fold_norms()
            folded = [body(images), body(images, in_place_norms=True)]
        assert not any(isinstance(m, FrozenBatchNorm2d) for m in body.modules())
        for maps in folded:
            for got, want in zip(maps, expected, strict=True):
                # the same sums in another order: float32 rounding of deep, large maps
                assert 0 < (got - want).norm() / want.norm() < 1e-5


def test_the_bfloat16_trunk_folds_its_norms_before_rounding(generator):
    model = taptr.build_model("small")  # a ConvNet trunk: cast, nothing to fold
    model.bfloat16_trunk()
    assert {p.dtype for p in model.backbone.parameters()} == {torch.bfloat16}
    body = _resnet(generator)
    images = torch.randn(1, 3, 64, 64, generator=generator)
    with torch.no_grad():
        exact = body(images)[-1]
        rounded = copy.deepcopy(body).to(torch.bfloat16)(images.bfloat16())[-1].float()
        body.fold_norms()
        folded = body.to(torch.bfloat16)(images.bfloat16())[-1].float()
    # one rounding of the folded weights instead of rounded outputs scaled and shifted
    assert (folded - exact).norm() < (rounded - exact).norm()


def test_folding_twice_changes_nothing(generator):
    body = _resnet(generator)
    body.fold_norms()
    once = copy.deepcopy(body.state_dict())
    body.fold_norms()  # as a second bfloat16 Predictor on the same model does
    for name, tensor in body.state_dict().items():
        assert torch.equal(tensor, once[name]), name
