"""Independent peer implementations, used only as references and benchmark peers.

Nothing in the production path imports this package. Each peer pulls in its own optional
(dev) dependency when it is used, not when this package is imported.
"""

from __future__ import annotations
