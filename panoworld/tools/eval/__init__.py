"""`runner.py eval`: one scene against its reference, whole datasets in the paper's table layouts."""
