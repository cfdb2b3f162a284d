"""Denoiser service: speech kept, noise taken out (DeepFilterNet 3), one stream's channels at a time."""
