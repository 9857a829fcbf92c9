"""`romannet eval` and `romannet plot`: the paper's evaluation protocol and learning curves.

metrics.py (pure metric arithmetic), runner.py (one run in a worker), protocol.py (the plan of runs, the
process pool, the journal), report.py (Markdown, JSON, PNG), curves.py (learning curves from run
directories), cli.py (the verbs).
"""
