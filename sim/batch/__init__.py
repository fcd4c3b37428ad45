"""Monte-Carlo batches: the batch file, executing its runs on a process pool or Ray,
statistics and reports, and regression runs against committed baselines."""
