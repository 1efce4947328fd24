"""Per-frame feature extractors (four levels at strides 4, 8, 16, 32) and input projections.

The papers' backbones are torchvision's ResNet-50 (TAPTRv2, TAPTRv3-R50) and ResNet-18
(TAPTRv3-R18) with frozen batch norm, so parameter names match both the official
checkpoints (``backbone.0.body.*``) and torchvision's ImageNet weights. `ConvNet` is a
light stand-in with group norm for tests and CPU-sized models.

At inference the ResNet can run its frozen batch norms in place (``in_place_norms``):
torchvision's `FrozenBatchNorm2d` writes ``x * scale`` and then ``+ shift`` as two new
tensors, a quarter of the trunk's time at 512 × 512 on two threads; every norm in a
ResNet reads a convolution output that nothing else holds, so it can be written over in
one pass with the same per-element arithmetic.

For the bfloat16 trunk (`taptr.model.taptr.TAPTR.bfloat16_trunk`) the norms are folded
into the convolutions before rounding (`ResNetBody.fold_norms`): one rounding of the
folded weights instead of a rounded convolution output scaled and shifted in bfloat16,
which moved the trunk's maps by 0.67x as much on the golden weights and skips the norm
passes.
"""

from __future__ import annotations

import itertools
import math

import torch
from torch import Tensor, nn
from torch.nn.utils.fusion import fuse_conv_bn_weights

from taptr.model.torchvision_pair import torchvision_mismatch

try:
    from torchvision.models import resnet18, resnet50
    from torchvision.models.resnet import BasicBlock, Bottleneck
    from torchvision.ops import FrozenBatchNorm2d
except RuntimeError as error:  # a torchvision built for another torch fails to register
    raise ModuleNotFoundError(torchvision_mismatch(error), name="torchvision") from None

from taptr.model.ops.row_blocks import tracks_grad


def frozen_norm_(norm: FrozenBatchNorm2d | nn.Identity, x: Tensor) -> Tensor:
    """``norm(x)`` written into ``x``, (N, C, H, W); without autograd only.

    The scale and shift are formed as torchvision forms them, and ``addcmul`` adds the
    shift to the rounded product, as ``x * scale + shift`` does. A norm folded into its
    convolution (`ResNetBody.fold_norms`) is an identity.
    """
    if isinstance(norm, nn.Identity):
        return x
    shift, scale = _shift_and_scale(norm)
    return torch.addcmul(shift, x, scale, out=x)


def _shift_and_scale(norm: FrozenBatchNorm2d) -> tuple[Tensor, Tensor]:
    """The norm's (1, C, 1, 1) shift and scale, kept on the norm until its tensors change.

    Four small operations per norm and frame otherwise (80 launches a frame for a
    ResNet-18); the key is each tensor's storage and version, so loading weights or
    moving the model makes them anew.
    """
    tensors = (norm.weight, norm.bias, norm.running_mean, norm.running_var)
    key = tuple((t.data_ptr(), t._version) for t in tensors)
    held = getattr(norm, "_taptr_shift_and_scale", None)
    if held is not None and held[0] == key and not torch.compiler.is_compiling():
        return held[1], held[2]
    scale = norm.weight * (norm.running_var + norm.eps).rsqrt()
    shift = norm.bias - norm.running_mean * scale
    pair = (shift.view(1, -1, 1, 1), scale.view(1, -1, 1, 1))
    if not torch.compiler.is_compiling():
        norm._taptr_shift_and_scale = (key, *pair)
    return pair


def _block_in_place(block: Bottleneck | BasicBlock, x: Tensor) -> Tensor:
    """``block(x)`` with its norms, residual sum and ReLUs written over their inputs."""
    out = frozen_norm_(block.bn1, block.conv1(x)).relu_()
    if isinstance(block, Bottleneck):
        out = frozen_norm_(block.bn2, block.conv2(out)).relu_()
        out = frozen_norm_(block.bn3, block.conv3(out))
    else:
        out = frozen_norm_(block.bn2, block.conv2(out))
    if block.downsample is None:
        return out.add_(x).relu_()
    convolution, norm = block.downsample
    return out.add_(frozen_norm_(norm, convolution(x))).relu_()


RESNETS = {"resnet50": resnet50, "resnet18": resnet18}


def _out_channels(block: Bottleneck | BasicBlock) -> int:
    last_norm = block.bn3 if isinstance(block, Bottleneck) else block.bn2
    return int(last_norm.weight.shape[0])


class ResNetBody(nn.Module):
    """ResNet-50 or ResNet-18 trunk without its classifier: the outputs of layer1..layer4.

    Shape:
        (N, 3, H, W) → four maps (N, C_l, H/s, W/s) at strides s = 4, 8, 16, 32, with
        C_l = (256, 512, 1024, 2048) for ResNet-50 and (64, 128, 256, 512) for ResNet-18.
    """

    def __init__(self, kind: str = "resnet50") -> None:
        """Creates the trunk, ``kind`` ``"resnet50"`` or ``"resnet18"``."""
        super().__init__()
        trunk = RESNETS[kind](weights=None, norm_layer=FrozenBatchNorm2d)
        stages = (trunk.layer1, trunk.layer2, trunk.layer3, trunk.layer4)
        self.channels = tuple(_out_channels(stage[-1]) for stage in stages)
        self.conv1, self.bn1, self.relu, self.maxpool = (
            trunk.conv1,
            trunk.bn1,
            trunk.relu,
            trunk.maxpool,
        )
        self.layer1, self.layer2, self.layer3, self.layer4 = (
            trunk.layer1,
            trunk.layer2,
            trunk.layer3,
            trunk.layer4,
        )

    def fold_norms(self) -> None:
        """Folds every frozen norm into the convolution before it, in float32; inference only.

        Each convolution gets the norm's scale in its weights and the shift as its bias,
        and the norm becomes an identity: the same function up to float rounding, with
        other parameter names (a folded trunk is not saved as a checkpoint). Norms already
        folded are left alone, so folding twice (a second bfloat16 `Predictor` on the same
        model) changes nothing.
        """
        pairs = [(self, "conv1", "bn1")]
        for stage in (self.layer1, self.layer2, self.layer3, self.layer4):
            for block in stage:
                names = (
                    ("conv1", "conv2", "conv3")
                    if isinstance(block, Bottleneck)
                    else ("conv1", "conv2")
                )
                pairs += [(block, name, name.replace("conv", "bn")) for name in names]
                if block.downsample is not None:
                    pairs.append((block.downsample, "0", "1"))
        for owner, conv_name, norm_name in pairs:
            conv, norm = getattr(owner, conv_name), getattr(owner, norm_name)
            if isinstance(norm, nn.Identity):
                continue
            weight, bias = fuse_conv_bn_weights(
                conv.weight.float(),
                None,
                norm.running_mean.float(),
                norm.running_var.float(),
                norm.eps,
                norm.weight.float(),
                norm.bias.float(),
            )
            conv.weight, conv.bias = weight, bias
            setattr(owner, norm_name, nn.Identity())

    def forward(self, images: Tensor, in_place_norms: bool = False) -> list[Tensor]:
        """Returns the four stage outputs.

        Args:
            images: (N, 3, H, W) frames.
            in_place_norms: run the frozen batch norms in place (see the module
                docstring); ignored where autograd records the forward.
        """
        stages = (self.layer1, self.layer2, self.layer3, self.layer4)
        if in_place_norms and not tracks_grad(self, images):
            x = self.maxpool(frozen_norm_(self.bn1, self.conv1(images)).relu_())
            levels = []
            for stage in stages:
                for block in stage:
                    x = _block_in_place(block, x)
                levels.append(x)
            return levels
        x = self.maxpool(self.relu(self.bn1(self.conv1(images))))
        levels = []
        for stage in stages:
            x = stage(x)
            levels.append(x)
        return levels


def _conv_block(in_channels: int, out_channels: int, stride: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False),
        nn.GroupNorm(math.gcd(8, out_channels), out_channels),
        nn.ReLU(inplace=True),
    )


class ConvNet(nn.Module):
    """A light four-level CNN (two 3×3 convolutions per stage, group norm).

    Shape:
        (N, 3, H, W) → four maps of ``channels[l]`` channels at strides 4, 8, 16, 32.
    """

    def __init__(self, channels: tuple[int, int, int, int]) -> None:
        super().__init__()
        self.channels = tuple(channels)
        c0 = channels[0]
        stages = [nn.Sequential(_conv_block(3, c0, 2), _conv_block(c0, c0, 2))]
        for c_in, c_out in itertools.pairwise(channels):
            stages.append(nn.Sequential(_conv_block(c_in, c_out, 2), _conv_block(c_out, c_out, 1)))
        self.stages = nn.ModuleList(stages)

    def forward(self, images: Tensor, in_place_norms: bool = False) -> list[Tensor]:
        """Returns the four stage outputs (group norms: ``in_place_norms`` changes nothing)."""
        levels = []
        x = images
        for stage in self.stages:
            x = stage(x)
            levels.append(x)
        return levels


class Backbone(nn.Module):
    """Wraps a trunk so that every kind exposes ``body`` and ``channels``.

    Shape:
        (N, 3, H, W) ImageNet-normalised frames → list of L maps (N, C_l, H_l, W_l).
    """

    def __init__(self, body: ResNetBody | ConvNet) -> None:
        super().__init__()
        self.body = body
        self.channels: tuple[int, ...] = tuple(body.channels)

    def forward(self, images: Tensor, in_place_norms: bool = False) -> list[Tensor]:
        """Returns the multi-scale maps of each image (``in_place_norms``: `ResNetBody`)."""
        return self.body(images, in_place_norms)


class InputProjections(nn.Module):
    """Per-level 1×1 convolution to d_model followed by GroupNorm(32).

    Shape:
        list of (N, C_l, H_l, W_l) → list of (N, C, H_l, W_l).
    """

    def __init__(self, in_channels: tuple[int, ...], d_model: int) -> None:
        super().__init__()
        self.levels = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(c, d_model, kernel_size=1), nn.GroupNorm(math.gcd(32, d_model), d_model)
            )
            for c in in_channels
        )
        for module in self.modules():
            if isinstance(module, nn.Conv2d) and module.bias is not None:
                nn.init.xavier_uniform_(module.weight, gain=1)
                nn.init.zeros_(module.bias)

    def forward(self, maps: list[Tensor]) -> list[Tensor]:
        """Projects every level."""
        return [project(x) for project, x in zip(self.levels, maps, strict=True)]
