"""`romannet sweep`: train every (recipe, seed) run one after another, evaluate each frozen on the same test
scenes with the oracle and random rows beside them, and tabulate mean, min and max over seeds.

    romannet sweep --config configs/experiments/stacking.toml --config configs/experiments/stacking-baseline.toml \\
        --seeds 1 2 3 --max-actions 2500 --out sweeps/stack-abl

Each run is a real `romannet up` subprocess and each evaluation a real `romannet eval` subprocess; the sweep
only starts processes and reads their files, so it resumes after Ctrl-C, a crash or a reboot by looking at
what is on disk (state.py). `<out>/` holds:

    sweep.json      the manifest: variants, seeds, --max-actions, --set overrides, evaluation settings
    sweep.log       this command's own log (progress lines included)
    runs/<variant>-s<seed>/    each training run (romannet up's run directory; or under --runs-dir)
    logs/<run>.log  logs/eval-<row>.log    each child's output
    eval/<run>/  eval/oracle/  eval/random/    each frozen evaluation's report.{md,json,png}
    results.md  results.json  curves.png       the table over seeds and the learning curves
"""
