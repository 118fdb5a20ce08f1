"""The paper studies, reproduced in simulation: :mod:`~layoutkit.studies.chen2024` (Chen et al.
2024, precision of a photodiode layout, eqs. 23-25) and :mod:`~layoutkit.studies.zhai2014` (Zhai
et al. 2014, camera attitude fly-around), and the tracking filter's simulated scenarios
(:mod:`~layoutkit.studies.filter_scenarios`, docs/filter.md); on real recordings,
:mod:`~layoutkit.studies.bitcraze_dataset` (the public Crazyflie Lighthouse logs: the firmware's
estimates and ours against motion capture, with the dataset's own metrics). They use the core and the workflows; nothing imports
them but the ``layoutkit study`` command, the scripts in ``studies/``, the benchmarks and the tests."""
