"""What runs are measured by and what is made of them: errors and recordings
(:mod:`.results`), summaries with one naming and one steady-state rule (:mod:`.summary`), plots
(:mod:`.plots`), and the studies: methods side by side (:mod:`.compare`), Monte Carlo
(:mod:`.montecarlo`), Tran et al.'s noise experiment (:mod:`.noise_study`), on a process pool
(:mod:`.parallel`). No rclpy."""
