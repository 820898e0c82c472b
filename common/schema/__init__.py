"""The schema's building blocks: how a config field is declared and its value checked (fields.py). A folder of
its own because both the root's config and the strategies' sections (common/exploration/) are written with it."""
