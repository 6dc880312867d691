"""A third-party lerobot policy type that reads the language ``task`` of each batch (tests).

Registered like any lerobot plugin policy: ``configuration_tiny_task`` registers the config
type ``tiny_task``; lerobot finds ``TinyTaskPolicy`` in ``modeling_tiny_task`` by convention.
"""
