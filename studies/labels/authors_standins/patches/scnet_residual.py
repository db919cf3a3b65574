"""A diagnostic patch, NOT part of running the authors' code unmodified (its run is labelled so).

SC-Net's ``RVPBlock.forward`` (sc-net/model.py) adds its residual in place onto the output of a ReLU
(``x2 += identity``); ReLU's backward needs that output, so autograd refuses the step whatever the data
(the driver shows it on random tensors). Loaded by ``launch.py --preload``, this gives the block the
same sum out of place, so that the rest of their train.py (loader, loss, optimiser, their accuracy
check on the labels) can be seen to run on an export.
"""

from __future__ import annotations

from typing import Any

import model  # their sc-net/model.py: the script's folder is first on sys.path


def _forward(self: Any, x: Any) -> Any:
    x1 = self.conv1(x)
    x2 = self.conv2(x1)
    if self.residual:
        x2 = x2 + x1
    return self.relu(x2)


model.RVPBlock.forward = _forward
