"""Empty: NBVNet's train.py imports ``torchvision.utils`` and never uses it."""
