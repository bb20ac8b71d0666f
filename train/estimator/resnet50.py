"""A ResNet-50 in plain ``torch.nn`` (no torchvision), and the peers' gaze network built on it.

:class:`ResNet50` has torchvision's parameter names and shapes, key for key (``conv1.weight``, ``bn1.*``,
``layer1.0.conv1.weight``, ..., ``layer1.0.downsample.0.weight``, ``fc.*``; 320 state-dict entries,
25,557,032 parameters with the 1000-way ``fc``), so a torchvision-format state dict loads into it unchanged.
Blocks are torchvision's "v1.5" bottleneck: the stride sits on the 3x3 convolution, as in the copies the
peers ship (GazeNeRF ``gaze_estimation/resnet.py:116-126``, ETH-XGaze ``modules/resnet.py:82-92``).

:class:`XGazeGazeNetwork` is the ETH-XGaze baseline network as GazeNeRF evaluates with it
(GazeNeRF ``gaze_estimation/xgaze_baseline_resnet.py:6-22``, after ETH-XGaze ``model.py:5-19``): the ResNet-50
trunk under the attribute ``gaze_network``, its output the 2048 globally pooled features (the trunk's
``fc`` is built, so it is in the state dict, but never run: GazeNeRF ``gaze_estimation/resnet.py:258-273``),
then ``gaze_fc = Sequential(Linear(2048, n))``. GazeNeRF's has n = 4, (gaze pitch, gaze yaw, head pitch,
head yaw) (``xgaze_baseline_resnet.py:11-20``): 25,565,228 parameters. ETH-XGaze's own released baseline has
n = 2, gaze only (``model.py:10-12``; GazeNeRF's copy ``gaze_estimation/orig_xgaze.py:10-12``).
"""

from __future__ import annotations

import torch
import torch.nn as nn

RESNET50_LAYERS = (3, 4, 6, 3)
"""Bottleneck blocks per stage (torchvision's ``resnet50``; GazeNeRF ``gaze_estimation/resnet.py:311``)."""
RESNET50_FEATURES = 2048
"""Channels after ``layer4``: 512 x the bottleneck's expansion 4."""


class Bottleneck(nn.Module):
    """1x1 (to ``width``) -> 3x3 (stride ``stride``) -> 1x1 (to 4 x ``width``), each with BatchNorm, ReLU
    between, plus the identity or a projected (1x1 conv + BN, ``downsample``) shortcut, then ReLU.
    [B, c_in, H, W] -> [B, 4 width, H / stride, W / stride]."""

    expansion = 4

    def __init__(self, c_in: int, width: int, stride: int = 1):
        super().__init__()
        c_out = width * self.expansion
        self.conv1 = nn.Conv2d(c_in, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, c_out, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(c_out)
        self.relu = nn.ReLU(inplace=True)
        # torchvision leaves the attribute None when the shapes already match: no keys for it then.
        self.downsample = None
        if stride != 1 or c_in != c_out:
            self.downsample = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), nn.BatchNorm2d(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        identity = x if self.downsample is None else self.downsample(x)
        return self.relu(out + identity)


class ResNet50(nn.Module):
    """torchvision's ``resnet50(num_classes)``: 7x7/2 stem, 3x3/2 max-pool, four bottleneck stages
    (64, 128, 256, 512 wide; strides 1, 2, 2, 2), global average pool, ``fc``.

    ``features(x [B, 3, H, W])`` -> [B, 2048] pooled features; ``forward`` -> [B, num_classes].
    """

    def __init__(self, num_classes: int = 1000):
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        c_in = 64
        for i, (blocks, width) in enumerate(zip(RESNET50_LAYERS, (64, 128, 256, 512))):
            stride = 1 if i == 0 else 2
            stage = []
            for b in range(blocks):
                stage.append(Bottleneck(c_in, width, stride if b == 0 else 1))
                c_in = width * Bottleneck.expansion
            setattr(self, f"layer{i + 1}", nn.Sequential(*stage))
        self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
        self.fc = nn.Linear(RESNET50_FEATURES, num_classes)
        # torchvision's initialisation, so an untrained instance behaves like one built there.
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """[B, 3, H, W] -> [B, 2048]: the globally pooled ``layer4`` output (``fc`` not applied)."""
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        return torch.flatten(self.avgpool(x), 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """[B, 3, H, W] -> [B, num_classes]."""
        return self.fc(self.features(x))


class XGazeGazeNetwork(nn.Module):
    """The ETH-XGaze baseline gaze network: ``gaze_fc(gaze_network.features(x))``.

    ``forward(x [B, 3, 224, 224] ImageNet-normalized RGB)`` -> [B, outputs] radians: (gaze pitch, gaze yaw)
    then, when ``outputs`` is 4 (GazeNeRF's), (head pitch, head yaw). The trunk keeps torchvision's 1000-way
    ``fc`` because the peers' checkpoints hold it (``gaze_network.fc.*``); it plays no part in the output.
    """

    def __init__(self, outputs: int = 4):
        super().__init__()
        if outputs not in (2, 4):
            raise ValueError(f"XGazeGazeNetwork.outputs: expected 2 (gaze) or 4 (gaze, head), got {outputs}")
        self.outputs = outputs
        self.gaze_network = ResNet50(num_classes=1000)
        self.gaze_fc = nn.Sequential(nn.Linear(RESNET50_FEATURES, outputs))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.gaze_fc(self.gaze_network.features(x))
