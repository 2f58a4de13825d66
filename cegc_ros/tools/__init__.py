"""Console scripts: one entry point per job; heavy imports stay inside main()."""
