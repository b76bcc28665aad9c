"""Applications built on the engine: the studies that measure it and the figures they draw.

This floor sits above the core (the rest of ``jaxmpm``): its modules import the core, and no
core module imports them. ``validation`` holds the validation studies (``python -m jaxmpm
validate``), ``fidelity`` the resolution and cross-code studies, ``bench`` the benchmarks
(``python -m jaxmpm bench``), ``element`` the material-point driver (``python -m jaxmpm
element``), ``avalanche`` the fields avalanche engineers measure on an S6 run, and ``plots``
every figure: a study returns data and draws through ``plots`` (matplotlib, the optional
``plot`` extra).
"""
