"""Tools for testing tisem against damaged input: the mutators and the oracle that the fuzz test
(`tests/test_fuzz_inputs.py`) and the longer campaign (`benchmarks/fuzz_inputs.py`) share."""
