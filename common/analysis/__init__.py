"""The statistics, tables and figures of evaluations and runs, which the evaluation (actor/evaluation/) and
the comparison across runs (deploy/) share: stats (episodes in, the tables' rows out), intervals (the
stratified bootstrap), tables (the evaluation's CSV and Markdown files), figures (the paper's comparison
figures) and plotting (what every figure shares)."""
