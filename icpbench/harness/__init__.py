"""The evaluation harness: runner, executors, results store, reports and progress output."""
