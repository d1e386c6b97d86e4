# Wire protocol (protocol/SPEC.md): the golden vectors must pass in BOTH codecs, with the same count.
.PHONY: test-protocol protocol-vectors

FT_VECTORS_DIR := $(ROOT)/protocol/vectors
FT_VECTORS_C := $(BUILD)/protocol/ft_vectors

# Regenerate protocol/vectors/*.tsv after a deliberate change of the generator (commit the result).
protocol-vectors: setup
	@$(PY) $(FT_VECTORS_DIR)/generate.py

test-protocol: cbuild
	@$(PY) $(FT_VECTORS_DIR)/generate.py --check
	@if [ ! -x "$(FT_VECTORS_C)" ]; then \
	  echo "test-protocol: FAIL: the C vector runner $(FT_VECTORS_C) was not built" \
	       "(protocol/CMakeLists.txt must build ft_vectors)"; exit 1; fi
	@c_out=$$("$(FT_VECTORS_C)" "$(FT_VECTORS_DIR)" 2>&1); c_rc=$$?; \
	py_out=$$($(PY) -m flytrack_host.protocol.vectors "$(FT_VECTORS_DIR)" 2>&1); py_rc=$$?; \
	c_line=$$(grep -E '^C codec: [0-9]+ vectors passed, [0-9]+ failed' <<<"$$c_out" | tail -1); \
	py_line=$$(grep -E '^Python codec: [0-9]+ vectors passed, [0-9]+ failed' <<<"$$py_out" | tail -1); \
	grep -v -E '^(C|Python) codec: ' <<<"$$c_out$$'\n'$$py_out" | sed '/^$$/d' | head -60; \
	echo "$${c_line:-C codec: no summary line (exit $$c_rc)}"; \
	echo "$${py_line:-Python codec: no summary line (exit $$py_rc)}"; \
	read -r c_n c_m < <(sed -E 's/.*: ([0-9]+) vectors passed, ([0-9]+) failed.*/\1 \2/' <<<"$$c_line"); \
	read -r py_n py_m < <(sed -E 's/.*: ([0-9]+) vectors passed, ([0-9]+) failed.*/\1 \2/' <<<"$$py_line"); \
	if [ -z "$$c_line" ] || [ -z "$$py_line" ] || [ $$c_rc -ne 0 ] || [ $$py_rc -ne 0 ] \
	   || [ "$$c_m" != 0 ] || [ "$$py_m" != 0 ] || [ "$$c_n" != "$$py_n" ]; then \
	  echo "test-protocol: FAIL (both codecs must pass every vector, the same number)"; exit 1; fi; \
	echo "test-protocol: OK, both codecs pass all $$py_n vectors"

PART_TARGETS += test-protocol protocol-vectors
