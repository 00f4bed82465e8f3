"""The fixed vocabularies of the options (no heavy imports: the command line reads them for --help)."""

MODES = ("exact", "paper")
COLOR_SPACES = ("rgb", "chroma")
COLOR_DEPTHS = ("auto", "8", "16")
SEED_MAX = (1 << 64) - 1
DEFAULT_CHUNK = 1 << 20
