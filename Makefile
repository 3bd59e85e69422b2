# batchrt -- Makefile.  Plain GNU make, no configure step.
#
#   make              library build/libbatchrt.a and the programs in build/
#   make test         build and run the test suite (last line: "N passed, N failed")
#   make debug        the same with -O0 -g and the library's internal checks
#   make sanitize     the test suite under AddressSanitizer + UBSan
#   make bench        benchmarks (figures printed, never pass/fail)
#   make clean
#
# == SETTINGS =============================================================
CC      ?= cc
OPT     ?= -O2
# The floating-point policy of batchrt.h: no FMA contraction, no fast-math,
# so every traversal order computes the same bits.
STD     = -std=c99 -D_POSIX_C_SOURCE=200809L -ffp-contract=off
# A curated warning list in the spirit of Lua's makefile.
WARN    = -Wall -Wextra -pedantic -Werror \
          -Wshadow -Wstrict-prototypes -Wmissing-prototypes -Wpointer-arith \
          -Wwrite-strings -Wundef -Wformat=2 -Wvla -Wcast-align \
          -Wold-style-definition -Wredundant-decls -Wnested-externs
CFLAGS  ?=
CFLAGS  += $(STD) $(WARN) $(OPT) $(XCFLAGS)
LDLIBS  = -lm
BUILD   ?= build
# == END OF SETTINGS ======================================================

LIB_SRC  = batchrt.c bvh.c svdag.c
LIB_OBJ  = $(LIB_SRC:%.c=$(BUILD)/%.o)
LIB      = $(BUILD)/libbatchrt.a
# Every examples/*.c is a program, except the shared helpers (common.c:
# options, errors, PNG; plot.c: SVG plots; rays.c: camera, random and bounce rays; scenes.c:
# the built-in procedural scenes) and the
# optional Embree tracer (built by "make embree" only).
EX_SHARED = examples/common.c examples/plot.c examples/rays.c examples/scenes.c
EX_COMMON = $(EX_SHARED:%.c=$(BUILD)/%.o)
EX_SRC   = $(filter-out $(EX_SHARED) examples/embree_trace.c, $(wildcard examples/*.c))
PROGRAMS = $(EX_SRC:examples/%.c=$(BUILD)/%)
TEST_SRC = $(wildcard tests/*.c)
TEST_OBJ = $(TEST_SRC:%.c=$(BUILD)/%.o)
TEST_BIN = $(BUILD)/run_tests

.PHONY: all test debug sanitize bench bench-batched clean
all: $(LIB) $(PROGRAMS)

$(BUILD)/%.o: %.c batchrt.h | $(BUILD)/examples $(BUILD)/tests
	$(CC) $(CFLAGS) -I. -c $< -o $@

$(BUILD)/examples/%.o: examples/%.c batchrt.h $(wildcard examples/*.h) | $(BUILD)/examples
	$(CC) $(CFLAGS) -I. -c $< -o $@

$(BUILD)/tests/%.o: tests/%.c $(wildcard tests/*.h) batchrt.h | $(BUILD)/tests
	$(CC) $(CFLAGS) -I. -c $< -o $@

$(BUILD)/examples $(BUILD)/tests:
	mkdir -p $@

$(LIB): $(LIB_OBJ)
	rm -f $@
	ar rcs $@ $^

$(BUILD)/%: $(BUILD)/examples/%.o $(EX_COMMON) $(LIB)
	$(CC) $(CFLAGS) $^ -o $@ $(LDLIBS)

$(TEST_BIN): $(TEST_OBJ) $(EX_COMMON) $(LIB)
	$(CC) $(CFLAGS) $^ -o $@ $(LDLIBS)

# The tests run programs from $(BUILD) too (command-line contracts).
test: all $(TEST_BIN)
	BRT_BUILD=$(BUILD) ./$(TEST_BIN) $(T)

debug:
	$(MAKE) test BUILD=build/debug OPT="-O0 -g" XCFLAGS="-DBRT_DEBUG"

sanitize:
	$(MAKE) test BUILD=build/sanitize OPT="-O1 -g -fno-omit-frame-pointer" \
	  XCFLAGS="-DBRT_DEBUG -fsanitize=address,undefined -fno-sanitize-recover=all"

bench: all
	./$(BUILD)/bench_bvh
	./$(BUILD)/bench_svdag

# Out of core: proxies on and off at 25 % of the geometry bytes (issue 4).
bench-batched: all
	./$(BUILD)/bench_batched landscape --scale 50

# == EMBREE (optional, cross-checking only; see README) ===================
# == END EMBREE ===========================================================

# == HARDENING (valgrind, fuzzing) ========================================
# == END HARDENING ========================================================

# == RENDER (demo, figures) ===============================================
# == END RENDER ===========================================================

clean:
	rm -rf build

.SECONDARY:
