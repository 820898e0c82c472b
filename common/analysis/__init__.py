"""The statistics, tables and figures of evaluations and runs, which the evaluation (actor/evaluation/) and
the comparison across runs (deploy/) share: stats (episodes in, the tables' rows out), intervals (the
stratified bootstrap), across_seeds (the IQM, the probability of improvement and the claims rule across training
runs, as rliable has them), tables (the evaluation's CSV and Markdown files), figures (the paper's comparison
figures) and plotting (what every figure shares)."""
