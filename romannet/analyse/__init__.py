"""Run diagnostics (`romannet analyse <what> RUN`): why a run does or does not learn, read from its recorded
episodes and checkpoints. Benchmarks, which measure speed, stay in bench/."""
