"""What is made of runs: summaries (:mod:`.summary`), plots, and the studies (methods side by
side, Monte Carlo, Tran et al.'s noise experiment) on a process pool. No rclpy."""
