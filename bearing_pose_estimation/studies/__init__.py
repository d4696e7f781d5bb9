"""What is made of runs: summaries with one naming and one steady-state rule (:mod:`.summary`)
of the recordings :mod:`metrics.results` measures, plots (:mod:`.plots`), and the studies:
methods side by side (:mod:`.compare`), Monte Carlo (:mod:`.montecarlo`), Tran et al.'s noise
experiment (:mod:`.noise_study`), on a process pool (:mod:`.parallel`). No rclpy."""
