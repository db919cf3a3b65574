"""A stand-in for torchvision, placed on PYTHONPATH only where torchvision is not installed.

The authors' grid trainers (NBVNet, MA-SCVP, SC-Net) import ``torchvision.transforms`` for ``Compose``
alone, and NBVNet's train.py also imports ``torchvision.utils`` without using it. torchvision's wheel
is built against one torch (and CUDA) release, so this chain of callables, which does what
``Compose`` does for their plain-Python transforms, is what a CPU-only machine gets instead.
"""
