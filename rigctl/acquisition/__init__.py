"""rigctl.acquisition: recording sessions on the rig (devices -> acquisition -> storage).

- :mod:`rigctl.acquisition.protocol` - TOML protocol files (validated, errors name the key and line) and
  Python-script protocols; ``load_protocol(path)``, ``Protocol.plan() -> list[PlannedTrial]``.
- :mod:`rigctl.acquisition.rig` - ``Rig.open(sim=True | hil=True | drum_port=, taxel_port=)``: the drum controller
  client, the taxel stream and (in simulation) the simulated rig behind one object; ``mount_texture``,
  ``press``, ``record_trial``, ``safe_stop``.
- :mod:`rigctl.acquisition.runner` - ``run_protocol(protocol, out_path, rig=...)``: trial by trial into a session
  file, with progress, Ctrl-C / stop / pause, failed trials and ``resume``.
- :mod:`rigctl.acquisition.calibration` - load-cell calibration with a known mass, per-taxel normalisation, and the
  rig config file (``~/.config/rigctl/rig.json``) that keeps them.
"""
