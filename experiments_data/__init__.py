"""The data jaxmpm ships (see README.md and manifest.json here), installed as the package
``jaxmpm.experiments_data`` so that ``calibration.data.data_dir()`` finds them in a
non-editable install. Nothing to import: read them with ``calibration.data``."""
