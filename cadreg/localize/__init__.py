"""Localization of one RGB-D frame in a site's map (DESIGN §1, steps 4–8). Entry point: `Localizer`."""

from .localizer import Localizer

__all__ = ["Localizer"]
