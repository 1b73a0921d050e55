"""hmepol: maximum state-entropy exploration with Markovian and recursive-history policies."""

__version__ = "0.1.0"
