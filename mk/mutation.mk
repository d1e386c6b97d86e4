# Mutation testing (issue 17): mutmut over the tracker, the synchroniser and the recorder, each against
# its fast unit tests, in a scratch copy. Slow; not part of `make test`. Prints the share killed.
.PHONY: mutation
PART_TARGETS += mutation

mutation: setup cbuild
	@$(PY) -c "import mutmut" 2>/dev/null || $(VENV)/bin/pip install -q mutmut==2.5.1
	@$(PY) scripts/mutation.py
