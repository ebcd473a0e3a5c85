"""pmdsim: simulation and evaluation of phase-measuring deflectometry (PMD).

Founding document: "The effects of pattern screen surface deformation on deflectometric
measurements — a simulation study". Conventions: docs/conventions.md.
"""

__version__ = "0.1.0"
