"""Training presets shrunk so a step takes milliseconds, shared by the tests that train."""

from __future__ import annotations

from pathlib import Path

__all__ = ["shrunk_preset", "tiny_act_preset", "tiny_preset"]


def shrunk_preset(tmp: Path, preset: str, name: str, edits: list[tuple[str, str]]) -> Path:
    """policy/presets/<preset>.toml with `edits` applied (each must match), written as <name>."""
    text = (Path(__file__).parents[1] / "policy" / "presets" / f"{preset}.toml").read_text()
    for old, new in [(f'name = "{preset}"', f'name = "{name}"'),
                     ("size = [60, 80]", "size = [24, 32]"), ("batch_size = 32", "batch_size = 4"),
                     ("checkpoint_every = 500", "checkpoint_every = 2"),
                     ("log_every = 50", "log_every = 1"), *edits]:
        assert old in text, old
        text = text.replace(old, new)
    path = tmp / f"{name}.toml"
    path.write_text(text)
    return path


def tiny_preset(tmp: Path) -> Path:
    """The cpu preset shrunk so a step takes milliseconds; same fields, same code path."""
    return shrunk_preset(tmp, "cpu", "tiny", [
        ("steps = 10000", "steps = 4"), ("crop_shape = [54, 72]", "crop_shape = [22, 30]"),
        ("down_dims = [48, 96, 192]", "down_dims = [16, 32, 64]"),
        ("diffusion_step_embed_dim = 64", "diffusion_step_embed_dim = 16"),
        ("spatial_softmax_num_keypoints = 32", "spatial_softmax_num_keypoints = 8")])


def tiny_act_preset(tmp: Path) -> Path:
    """policy/presets/act.toml shrunk so a step takes milliseconds; same fields, same path."""
    return shrunk_preset(tmp, "act", "tiny_act", [
        ("steps = 30000", "steps = 4"), ("chunk_size = 32", "chunk_size = 8"),
        ("n_action_steps = 8", "n_action_steps = 4"), ("dim_model = 256", "dim_model = 32"),
        ("n_heads = 8", "n_heads = 2"), ("dim_feedforward = 1024", "dim_feedforward = 64"),
        ("n_encoder_layers = 4", "n_encoder_layers = 1"),
        ("n_vae_encoder_layers = 4", "n_vae_encoder_layers = 1")])
