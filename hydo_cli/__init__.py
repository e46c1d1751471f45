"""hydo's command line: ``hydo train | eval | export | deploy``. Start reading at ``main.py``."""

__version__ = "0.1.0"
