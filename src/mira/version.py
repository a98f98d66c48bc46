"""The version of MIRA (``mira.__version__``), in a module of its own so that every part of MIRA can
read it without importing the package's public interface."""

__version__ = "0.1.0"
