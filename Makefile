# batchrt -- Makefile.  Plain GNU make, no configure step.
#
#   make              library build/libbatchrt.a and the programs in build/
#   make test         build and run the test suite (last line: "N passed, N failed")
#   make test-long    the tests too slow for "make test" (a real input past a split)
#   make debug        the same with the library's assert()ed invariants (BRT_DEBUG)
#   make sanitize     the test suite under AddressSanitizer + UBSan
#   make tsan         the threaded tests (and layer 6's processes as threads) under ThreadSanitizer
#   make bench        benchmarks (figures printed, never pass/fail)
#   make bench-threads  speed-ups at 1 and 2 threads (README, "Threads")
#   make bench-pbrt   pbrt and OBJ reading speed on the same triangles
#   make bench-order  the bottom level with the proxy entry's clip and order
#                     (layers 10, 11), and proxies in core
#   make mutants      mutation testing of the suite (tests/mutants/)
#   make mutants-sample [N=40] [SEED=1] [FILES=...]  mutants drawn at random
#   make install      library, header and batchrt.pc under $(DESTDIR)$(PREFIX)
#   make uninstall    removes them; make install-check: see INSTALL below
#   make clean
#   make V=1 ...      show the full command lines
#
# == SETTINGS =============================================================
CC      ?= cc
# -O2, not -O3: -O3 unrolls the BVH walk into more instructions (callgrind
# on build/bench_bvh counts them).
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
# -pthread: the pool of base.c (README, "Threads"), compile and link.
CFLAGS  += $(STD) $(WARN) $(OPT) -pthread $(XCFLAGS)
LDLIBS  = -lm
BUILD   ?= build
# The tests and the fuzz targets are compiled with the library's hooks
# (testing.h, as SQLite's SQLITE_TEST), and link a copy of the library
# compiled with them ($(TEST_LIB)); $(LIB) and the programs have none.
TESTING = -DBRT_TESTING
# "make V=1" shows the full command lines.
V       ?= 0
# == END OF SETTINGS ======================================================

ifeq ($(V),0)
Q   = @
SAY = @printf '  %-6s %s\n'
else
Q   =
SAY = @true
endif

LIB_SRC  = batchrt.c scene.c world.c mesh.c bvh.c svdag.c base.c
LIB_OBJ  = $(LIB_SRC:%.c=$(BUILD)/%.o)
LIB      = $(BUILD)/libbatchrt.a
# examples/ by kind: tutorials/ (the two APIs in a page each), tools/ (the
# programs a user runs), bench/ (benchmarks) and lib/ (the support code they
# share, not a program: options and errors, mesh and pbrt-v4 input, rays,
# the built-in scenes, plots, the referee, render's reports).  Every .c of
# the first three is a program, build/NAME, except the optional Embree and
# MPI tracers (built by "make embree" and "make mpi" only).
EX_KINDS  = tutorials tools bench
EX_SHARED = $(wildcard examples/lib/*.c)
EX_HDRS   = $(wildcard examples/lib/*.h)
EX_INC    = -Iexamples/lib
EX_COMMON = $(EX_SHARED:%.c=$(BUILD)/%.o)
EX_SRC   = $(filter-out examples/tools/embree_trace.c examples/tools/mpi_trace.c, \
             $(foreach k,$(EX_KINDS),$(wildcard examples/$(k)/*.c)))
PROGRAMS = $(patsubst %.c,$(BUILD)/%,$(notdir $(EX_SRC)))
TEST_SRC = $(wildcard tests/*.c)
TEST_OBJ = $(TEST_SRC:%.c=$(BUILD)/%.o)
TEST_BIN = $(BUILD)/run_tests
TEST_LIB_OBJ = $(LIB_SRC:%.c=$(BUILD)/tests/core/%.o)
TEST_LIB = $(BUILD)/tests/libbatchrt_testing.a

.PHONY: all test debug sanitize tsan bench bench-batched clean mutants
all: $(LIB) $(PROGRAMS)

$(BUILD)/%.o: %.c batchrt.h internal.h testing.h | $(BUILD)/examples $(BUILD)/tests
	$(SAY) CC $<
	$(Q)$(CC) $(CFLAGS) -I. -c $< -o $@

$(BUILD)/examples/%.o: examples/%.c batchrt.h $(EX_HDRS)
	$(SAY) CC $<
	$(Q)mkdir -p $(@D)
	$(Q)$(CC) $(CFLAGS) -I. $(EX_INC) -c $< -o $@

$(BUILD)/tests/%.o: tests/%.c $(wildcard tests/*.h) $(EX_HDRS) batchrt.h internal.h testing.h | $(BUILD)/tests
	$(SAY) CC $<
	$(Q)$(CC) $(CFLAGS) $(TESTING) -I. -c $< -o $@

# The library again with its hooks (BRT_TESTING), for the test runner.
$(BUILD)/tests/core/%.o: %.c batchrt.h internal.h testing.h | $(BUILD)/tests/core
	$(SAY) CC "$< (BRT_TESTING)"
	$(Q)$(CC) $(CFLAGS) $(TESTING) -I. -c $< -o $@

$(BUILD)/examples $(BUILD)/tests $(BUILD)/tests/core:
	$(Q)mkdir -p $@

$(LIB): $(LIB_OBJ)
	$(SAY) AR $@
	$(Q)rm -f $@
	$(Q)ar rcs $@ $^

$(TEST_LIB): $(TEST_LIB_OBJ)
	$(SAY) AR $@
	$(Q)rm -f $@
	$(Q)ar rcs $@ $^

# build/NAME from examples/KIND/NAME.c, one link rule per kind (but
# EX_TESTING's, below).
EX_TESTING = $(BUILD)/bench_order
define EX_LINK
$$(filter-out $$(EX_TESTING),$$(patsubst examples/$(1)/%.c,$$(BUILD)/%,$$(filter examples/$(1)/%,$$(EX_SRC)))): \
  $$(BUILD)/%: $$(BUILD)/examples/$(1)/%.o $$(EX_COMMON) $$(LIB)
	$$(SAY) LINK $$@
	$$(Q)$$(CC) $$(CFLAGS) $$^ -o $$@ $$(LDLIBS)
endef
$(foreach k,$(EX_KINDS),$(eval $(call EX_LINK,$(k))))

# The one program that reads the library's counters (testing.h): build/
# bench_order (make bench-order) counts BVH node visits and times the
# batches' intersections through hooks that only $(TEST_LIB) holds, so it
# is compiled with $(TESTING) and links that copy; every other program
# links $(LIB), which has no hook.
$(EX_TESTING:$(BUILD)/%=$(BUILD)/examples/bench/%.o): CFLAGS += $(TESTING)
$(EX_TESTING:$(BUILD)/%=$(BUILD)/examples/bench/%.o): internal.h testing.h
$(EX_TESTING): $(BUILD)/%: $(BUILD)/examples/bench/%.o $(EX_COMMON) $(TEST_LIB)
	$(SAY) LINK $@
	$(Q)$(CC) $(CFLAGS) $^ -o $@ $(LDLIBS)

$(TEST_BIN): $(TEST_OBJ) $(EX_COMMON) $(TEST_LIB)
	$(SAY) LINK $@
	$(Q)$(CC) $(CFLAGS) $^ -o $@ $(LDLIBS)

# The allocation-failure shim of the oom: tests (tests/oom/failalloc.c),
# preloaded into the programs they run; it is empty but on glibc, and
# those tests SKIP then.
FAILALLOC = $(BUILD)/tests/failalloc.so
$(FAILALLOC): tests/oom/failalloc.c | $(BUILD)/tests
	$(SAY) CC "$< (shared)"
	$(Q)$(CC) $(CFLAGS) -fPIC -shared $< -o $@

# The tests run programs from $(BUILD) too (command-line contracts).  The
# install check (below) comes first, so that the runner's line stays last,
# and only without a filter T.  The MPI tracer is built for the tests when
# mpicc exists, in the plain build only (the sanitizers' runtimes and Open
# MPI's do not mix; those runs say SKIP).
MPICC ?= mpicc
MPI_FOR_TESTS = $(if $(filter build,$(BUILD)),$(if $(shell command -v $(MPICC) 2>/dev/null),$(BUILD)/mpi_trace))
# The fuzz replay program is linked too, though the runner replays the
# corpus itself: it links what the fuzz targets link, which only CI's fuzz
# smoke would build otherwise.
test: all $(TEST_BIN) $(FAILALLOC) $(MPI_FOR_TESTS) $(BUILD)/tests/fuzz/replay $(if $(T),,install-check)
	BRT_BUILD=$(BUILD) ./$(TEST_BIN) $(T)

# Mutation testing (tests/mutants/): each mutant in tests/mutants/mutants.txt
# weakens one mechanism in a copy of the tree and must make its tests fail;
# prints a table (README, Tests).  M=NAME runs the mutants whose names
# contain NAME.  Not part of "make test": it runs the suite once per mutant.
mutants: all $(TEST_BIN)
	sh tests/mutants/run.sh $(M)

# Mutants nobody chose (tests/mutants/sample.sh): N mutation operators at
# lines drawn at random (SEED) from FILES, each run against the whole
# suite, stopping at its first failure; prints the kill rate and every
# survivor's diff (README, Tests).  Slow: minutes per surviving mutant.
N     ?= 40
SEED  ?= 1
FILES ?= $(LIB_SRC)
.PHONY: mutants-sample
mutants-sample: all $(TEST_BIN)
	sh tests/mutants/sample.sh $(N) $(SEED) $(FILES)

# The suite with the library's assert()ed invariants compiled in (BRT_DEBUG:
# heap order, walk keys, cache pins and bytes, queued rays admitted by their
# proxy).  -O1, not -O0: the asserts are the point, and CI runs it whole.
debug:
	$(MAKE) --no-print-directory test BUILD=build/debug OPT="-O1 -g" XCFLAGS="-DBRT_DEBUG"

sanitize:
	$(MAKE) --no-print-directory test BUILD=build/sanitize OPT="-O1 -g -fno-omit-frame-pointer" \
	  XCFLAGS="-DBRT_DEBUG -fsanitize=address,undefined -fno-sanitize-recover=all"

# The threaded tests (names starting "threads") under ThreadSanitizer: any
# report fails (halt_on_error).
tsan:
	$(MAKE) --no-print-directory all build/tsan/run_tests BUILD=build/tsan OPT="-O1 -g" \
	  XCFLAGS="-fsanitize=thread"
	BRT_BUILD=build/tsan TSAN_OPTIONS="halt_on_error=1 exitcode=66" ./build/tsan/run_tests threads exchange:

bench: all
	./$(BUILD)/bench_bvh
	./$(BUILD)/bench_svdag

# Out of core: proxies on and off at 25 % of the geometry bytes (README, Benchmarks).
bench-batched: all
	./$(BUILD)/bench_batched landscape --scale 0.8

# Tokenizing speed of the pbrt reader (issue 29): build/bench_pbrt opens
# and streams the same triangles as an OBJ and as a pbrt file with one
# inline trianglemesh (written here from the OBJ's own number text: its
# "v x y z" and "f a b c" lines), PBRT_REPEAT times each, and checks that
# both stream the same bits.  Wall-clock seconds, best and worst; a
# Markdown table.  Figures only, never pass/fail.
PBRT_MESH   ?= ../shared/data/meshes/dragon.obj.gz
PBRT_REPEAT ?= 7
PBRT_BENCH  ?= /tmp/batchrt-bench-pbrt
.PHONY: bench-pbrt
bench-pbrt: all
	@mkdir -p $(PBRT_BENCH); d=$(PBRT_BENCH); \
	gzip -dcf $(PBRT_MESH) > $$d/mesh.obj || exit 1; \
	{ echo WorldBegin; echo 'Shape "trianglemesh" "point3 P" ['; awk '$$1 == "v" { print $$2, $$3, $$4 }' $$d/mesh.obj; \
	  echo '] "integer indices" ['; awk '$$1 == "f" { print $$2 - 1, $$3 - 1, $$4 - 1 }' $$d/mesh.obj; echo ']'; \
	} > $$d/mesh.pbrt || exit 1; \
	echo "$(PBRT_MESH) as OBJ and as pbrt (one inline trianglemesh)"; \
	./$(BUILD)/bench_pbrt $$d/mesh.obj $$d/mesh.pbrt --repeat $(PBRT_REPEAT)

# == EMBREE (optional, cross-checking only; see README) ===================
# "make embree" builds $(BUILD)/embree_trace against Embree 3 (Debian:
# libembree-dev) and fails with a plain message when Embree is missing;
# "all" and "test" never need it (tests/test_embree.c skips without it).
EMBREE_LIBS ?= -lembree3
EMBREE_PROBE = printf '\#include <embree3/rtcore.h>\n' | $(CC) -E -x c - >/dev/null 2>&1
.PHONY: embree bench-embree
embree: $(LIB) $(EX_COMMON)
	@$(EMBREE_PROBE) || { echo "embree: Embree 3 not found (no <embree3/rtcore.h>);" \
	  "install libembree-dev (Debian) to build $(BUILD)/embree_trace"; exit 1; }
	@$(MAKE) --no-print-directory $(BUILD)/embree_trace

$(BUILD)/embree_trace: $(BUILD)/examples/tools/embree_trace.o $(EX_COMMON) $(LIB)
	$(SAY) LINK $@
	$(Q)$(CC) $(CFLAGS) $^ -o $@ $(LDLIBS) $(EMBREE_LIBS)

# MPI (README, "Beyond one machine"): build/mpi_trace with $(MPICC), only
# when it exists; the library and the other programs never need MPI.
# Open MPI's headers are included as system headers (-isystem), so that
# our warning flags apply to our code only.
.PHONY: mpi bench-mpi
mpi: $(LIB) $(EX_COMMON)
	@command -v $(MPICC) >/dev/null 2>&1 || { echo "mpi: $(MPICC) not found;" \
	  "install openmpi-bin and libopenmpi-dev (Debian) to build $(BUILD)/mpi_trace"; exit 1; }
	@$(MAKE) --no-print-directory $(BUILD)/mpi_trace $(BUILD)/tests/mpi_trace_small

$(BUILD)/mpi_trace: examples/tools/mpi_trace.c $(EX_COMMON) $(LIB) batchrt.h $(EX_HDRS)
	$(SAY) MPICC $@
	$(Q)$(MPICC) $(CFLAGS) -I. $(EX_INC) $$($(MPICC) --showme:incdirs 2>/dev/null | sed 's/[^ ]*/-isystem &/g') \
	  examples/tools/mpi_trace.c $(EX_COMMON) $(LIB) -o $@ $(LDLIBS)

# The MPI tracer's thresholds under test.  $(BUILD)/tests/mpi_trace_small: mpi_trace gathering results in chunks of
# MPI_SMALL_RESULTS instead of 2^20, so that tests/test_mpi.c crosses that
# split with a few thousand rays (the shipped $(BUILD)/mpi_trace keeps
# 2^20); built by "make mpi" and for "make test" when mpicc exists.
# "make test-long": the tests too slow for "make test" (names holding
# "long:"; BRT_TEST_LONG=1, else they say SKIP): the shipped binary past
# 2^20 results on one rank, held against trace --direct.
MPI_SMALL_RESULTS = 1000
.PHONY: test-long
test: $(patsubst %/mpi_trace,%/tests/mpi_trace_small,$(MPI_FOR_TESTS))
# The mutants run the suite too: without these programs their oom: and
# mpi: tests would say SKIP and every mutant of them would survive.
mutants mutants-sample: $(FAILALLOC) $(MPI_FOR_TESTS) $(patsubst %/mpi_trace,%/tests/mpi_trace_small,$(MPI_FOR_TESTS))
$(BUILD)/tests/mpi_trace_small: examples/tools/mpi_trace.c $(EX_COMMON) $(LIB) batchrt.h $(EX_HDRS) | $(BUILD)/tests
	$(SAY) MPICC $@
	$(Q)$(MPICC) $(CFLAGS) -DRESULTS_PER_MESSAGE=$(MPI_SMALL_RESULTS) -I. $(EX_INC) \
	  $$($(MPICC) --showme:incdirs 2>/dev/null | sed 's/[^ ]*/-isystem &/g') \
	  examples/tools/mpi_trace.c $(EX_COMMON) $(LIB) -o $@ $(LDLIBS)
test-long: all $(TEST_BIN) $(MPI_FOR_TESTS)
	BRT_BUILD=$(BUILD) BRT_TEST_LONG=1 ./$(TEST_BIN) 'long:'

# The network with and without proxies (README, "Beyond one machine"):
# mpi_trace over the instanced landscape at 2, 4 and 8 ranks (on this
# machine's cores: --oversubscribe), and at 4 ranks the round-robin
# ownership, camera and bounce rays, each rank's
# geometry cache at MPI_MEMORY, a modelled network of MPI_NET per second
# (--net-speed) and disk of MPI_DISK (--disk-speed).  Counts are the last
# run's (loads depend on when messages arrive), seconds the best of
# MPI_REPEAT.  Prints a Markdown table; figures only, never pass/fail.
MPI_SCALE  ?= 20
MPI_RAYS   ?= 200000
MPI_MEMORY ?= 16M
MPI_NET    ?= 1G
MPI_DISK   ?= 200M
MPI_REPEAT ?= 3
MPI_BENCH  ?= /tmp/batchrt-bench-mpi
# Open MPI refuses root unless told; told here, for this command only.
MPI_AS_ROOT = $(shell test "$$(id -u)" = 0 && echo env OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1)
MPIRUN     ?= $(MPI_AS_ROOT) mpirun --oversubscribe
bench-mpi: all mpi
	@mkdir -p $(MPI_BENCH)
	@./$(BUILD)/mkscene landscape $(MPI_BENCH)/land.pbrt --scale $(MPI_SCALE) >/dev/null
	@for k in camera bounce; do ./$(BUILD)/raygen $(MPI_BENCH)/land.pbrt $(MPI_BENCH)/$$k.rays \
	  --kind $$k --count $(MPI_RAYS) >/dev/null || exit 1; done
	@echo "Instanced landscape, scale $(MPI_SCALE), $(MPI_RAYS) camera + $(MPI_RAYS) bounce rays," \
	  "--memory $(MPI_MEMORY) per rank, --net-speed $(MPI_NET), --disk-speed $(MPI_DISK);" \
	  "seconds: the best of $(MPI_REPEAT) runs:"; echo; \
	echo "| ranks | ownership | proxies | rays sent | messages | network MB | loads | disk MB | seconds |"; \
	echo "|---:|---|---|---:|---:|---:|---:|---:|---:|"; \
	v() { sed -n "/\"total\"/,/}/s/.*\"$$1\": \([0-9.]*\).*/\1/p" $(MPI_BENCH)/s.json; }; \
	for run in 2:runs 4:runs 4:round-robin 8:runs; do n=$${run%%:*}; a=$${run#*:}; \
	for p in on off; do sent=0; msgs=0; net=0; loads=0; disk=0; secs=0; \
	  for k in camera bounce; do best=; \
	    for r in $$(seq $(MPI_REPEAT)); do \
	      $(MPIRUN) -np $$n ./$(BUILD)/mpi_trace $(MPI_BENCH)/land.pbrt $(MPI_BENCH)/$$k.rays \
	        $(MPI_BENCH)/out.hits --scene $(MPI_BENCH)/land.brs --memory $(MPI_MEMORY) \
	        --net-speed $(MPI_NET) --disk-speed $(MPI_DISK) --stats $(MPI_BENCH)/s.json --assign $$a \
	        $$(test $$p = off && echo --no-proxy) </dev/null || exit 1; \
	      t=$$(sed -n 's/.*"seconds": \([0-9.]*\).*/\1/p' $(MPI_BENCH)/s.json); \
	      best=$$(awk -v a="$$best" -v b=$$t 'BEGIN { print (a == "" || b < a) ? b : a }'); \
	    done; \
	    sent=$$((sent + $$(v rays_sent))); msgs=$$((msgs + $$(v messages_sent))); \
	    net=$$((net + $$(v bytes_sent))); loads=$$((loads + $$(v batch_loads))); \
	    disk=$$((disk + $$(v disk_bytes_read))); \
	    secs=$$(awk -v a=$$secs -v b=$$best 'BEGIN { print a + b }'); \
	  done; \
	  awk -v n=$$n -v a=$$a -v p=$$p -v s=$$sent -v m=$$msgs -v b=$$net -v l=$$loads -v d=$$disk -v t=$$secs \
	    'BEGIN { printf "| %d | %s | %s | %d | %d | %.1f | %d | %.1f | %.2f |\n", n, a, p, s, m, b / 1e6, l, d / 1e6, t }'; \
	done; done

# Speed side by side: single-thread Mrays/s of trace --direct and
# embree_trace (default and --robust) on the same ray files (camera,
# random, bounce; 1M each) of the shared dragon (871K triangles), the best
# of EMBREE_REPEAT runs each (the machine may be shared), then their
# agreement from build/hitdiff.  The batched mode in core, with its
# points decoded (layer 8, the default) and kept quantized (--no-decode).
# Then the BVH's bytes per triangle in
# memory and in the blobs (the batched run's geometry bytes: every point
# loaded once), and its build time.  Figures only, never pass/fail.  trace
# runs with --threads 1, as Embree does (its default, all cores, had
# given batchrt two cores against Embree's one since the thread pool).
EMBREE_MESH   ?= ../shared/data/meshes/dragon.obj.gz
EMBREE_RAYS   ?= 1000000
EMBREE_REPEAT ?= 3
EMBREE_BENCH  ?= /tmp/batchrt-bench-embree
bench-embree: all embree
	@mkdir -p $(EMBREE_BENCH)
	@rm -f $(EMBREE_BENCH)/scene.brs   # built afresh by the first batched run (not timed)
	@m=$(EMBREE_BENCH)/$$(basename $(EMBREE_MESH) .gz); \
	test -s $$m || gzip -dc $(EMBREE_MESH) > $$m || exit 1; \
	best() { out=$$1; shift; for i in $$(seq $(EMBREE_REPEAT)); do \
	    "$$@" --stats $$out.json || exit 1; \
	    sed -n 's/.*"mrays_per_second": *\([0-9.eE+-]*\).*/\1/p' $$out.json; \
	  done | sort -g | tail -1; }; \
	echo "$$m, $(EMBREE_RAYS) rays per kind, one thread, best of $(EMBREE_REPEAT) (cold: one trace run each), Mrays/s"; \
	echo; echo "| rays | direct | batched | quantized | Embree | robust | direct / Embree | batched / Embree |"; \
	echo "|---|---:|---:|---:|---:|---:|---:|---:|"; \
	for k in camera random bounce; do d=$(EMBREE_BENCH)/$$k; \
	  ./$(BUILD)/raygen $$m $$d.rays --kind $$k --count $(EMBREE_RAYS) || exit 1; \
	  b=$$(best $$d.brt ./$(BUILD)/trace $$m $$d.rays $$d.brt.hits --threads 1); \
	  bb=$$(best $$d.bat ./$(BUILD)/trace $$m $$d.rays $$d.bat.hits --threads 1 --batched --scene $(EMBREE_BENCH)/scene.brs); \
	  bq=$$(best $$d.baq ./$(BUILD)/trace $$m $$d.rays $$d.baq.hits --threads 1 --batched --no-decode --scene $(EMBREE_BENCH)/scene.brs); \
	  cmp -s $$d.brt.hits $$d.bat.hits && cmp -s $$d.brt.hits $$d.baq.hits || { echo "$$k: batched hits differ from direct"; exit 1; }; \
	  e=$$(best $$d.emb ./$(BUILD)/embree_trace $$m $$d.rays $$d.emb.hits); \
	  r=$$(best $$d.rob ./$(BUILD)/embree_trace $$m $$d.rays $$d.rob.hits --robust); \
	  awk -v k=$$k -v b=$$b -v bb=$$bb -v bq=$$bq -v e=$$e -v r=$$r 'BEGIN { \
	    printf "| %s | %.2f | %.2f | %.2f | %.2f | %.2f | %.2f | %.2f |\n", k, b, bb, bq, e, r, b / e, bb / e }'; \
	done; echo; \
	sed -n 's/.*"bvh_bytes_per_triangle": *\([0-9.eE+-]*\).*/batchrt BVH bytes per triangle in memory (direct mode: quantized and resident layouts): \1/p; s/.*"build_seconds": *\([0-9.eE+-]*\).*/batchrt BVH build seconds (direct mode): \1/p' $(EMBREE_BENCH)/bounce.brt.json; \
	tris=$$(awk '/^f /{ t += NF - 3 } END { print t }' $$m); \
	sed -n 's/.*"geometry_bytes": *\([0-9]*\).*/\1/p' $(EMBREE_BENCH)/bounce.bat.json | \
	  awk -v t=$$tris '{ printf "batchrt blob bytes per triangle on disk (batching points, %d triangles): %.2f\n", t, $$1 / t }'; \
	sed -n 's/.*"decoded_bytes": *\([0-9]*\).*/\1/p' $(EMBREE_BENCH)/bounce.bat.json | \
	  awk -v t=$$tris '{ printf "batchrt decoded bytes per triangle in memory (batched in core, layer 8): %.2f\n", $$1 / t }'; \
	sed -n 's/.*"load_seconds": *\([0-9.eE+-]*\).*/batchrt batched load seconds (read, check, decode every point; its last bounce run): \1/p' $(EMBREE_BENCH)/bounce.bat.json; \
	echo "warm (cached) figures: make bench (build/bench_bvh)"; \
	for k in camera random bounce; do d=$(EMBREE_BENCH)/$$k; \
	  for x in emb rob; do printf '%s vs %s: ' $$k $$x; \
	    ./$(BUILD)/hitdiff $$d.brt.hits $$d.$$x.hits --max-disagree 1e-4 | tail -1; \
	  done; \
	done

# The cost of instancing (issue 28): trace --direct, one thread, on a mesh
# and on the same mesh as the one instance of a pbrt file under the
# identity; hits equal but for the instance number (checked).  Mrays/s,
# best of INSTANCING_REPEAT; a Markdown table.
INSTANCING_SCALE  ?= 10
INSTANCING_RAYS   ?= 1000000
INSTANCING_REPEAT ?= 3
INSTANCING_BENCH  ?= /tmp/batchrt-bench-instancing
.PHONY: bench-instancing
bench-instancing: all
	@mkdir -p $(INSTANCING_BENCH); d=$(INSTANCING_BENCH); \
	./$(BUILD)/mkscene crown $$d/crown.ply --scale $(INSTANCING_SCALE) > /dev/null || exit 1; \
	printf 'WorldBegin\nObjectBegin "crown"\nShape "plymesh" "string filename" "crown.ply"\nObjectEnd\nObjectInstance "crown"\n' > $$d/crown.pbrt; \
	best() { out=$$1; shift; for i in $$(seq $(INSTANCING_REPEAT)); do \
	    "$$@" --threads 1 --stats $$out.json > /dev/null || exit 1; \
	    sed -n 's/.*"mrays_per_second": *\([0-9.eE+-]*\).*/\1/p' $$out.json; \
	  done | sort -g | tail -1; }; \
	echo "the crown at scale $(INSTANCING_SCALE), $(INSTANCING_RAYS) rays per kind, trace --direct, one thread, best of $(INSTANCING_REPEAT), Mrays/s"; \
	echo; echo "| rays | mesh | one instance | instance / mesh |"; echo "|---|---:|---:|---:|"; \
	for k in camera random bounce; do \
	  ./$(BUILD)/raygen $$d/crown.ply $$d/$$k.rays --kind $$k --count $(INSTANCING_RAYS) || exit 1; \
	  m=$$(best $$d/m ./$(BUILD)/trace $$d/crown.ply $$d/$$k.rays $$d/m.hits); \
	  i=$$(best $$d/i ./$(BUILD)/trace $$d/crown.pbrt $$d/$$k.rays $$d/i.hits); \
	  awk -v k=$$k -v m=$$m -v i=$$i 'BEGIN { printf "| %s | %.2f | %.2f | %.2f |\n", k, m, i, i / m }'; \
	done

# == END EMBREE ===========================================================

# == HARDENING (valgrind, fuzzing) ========================================
#   make valgrind      the test suite, and the programs it runs, under
#                      memcheck: any error or leak fails (T=... filters)
#   make fuzz          libFuzzer + ASan + UBSan builds of the five readers
#                      (tests/fuzz/fuzz_*.c) in $(BUILD)/fuzz, each run for
#                      FUZZ_SECONDS from tests/corpus/NAME; new inputs go to
#                      $(BUILD)/fuzz/corpus/NAME, crashes to $(BUILD)/fuzz/
#   make fuzz-replay   tests/corpus through the same targets, plain build
#   make fuzz-smoke    CI's smoke (.ci/run): "make fuzz" for FUZZ_SMOKE_SECONDS
#                      (60) a target, one line each, failing on the first
#                      problem; one SKIP line when $(FUZZ_CC) cannot build
#                      libFuzzer programs
# The targets (tests/fuzz/targets.c) are also linked into run_tests, whose
# "hardening:" tests replay tests/corpus on every "make test".
FUZZ_TARGETS = obj ply scene rays pbrt
FUZZ_SECONDS ?= 600
FUZZ_CC ?= clang
# The fuzz targets refine loopsubdiv shapes to at most 2^14 triangles (the
# programs: 2^20), so that no input of a few bytes costs libFuzzer more
# than its time per input under the sanitizers; the limit's code is the same.
FUZZ_FLAGS = $(STD) $(WARN) $(TESTING) -O1 -g -fno-omit-frame-pointer \
             -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=all -DEX_LOOP_MAX_TRIANGLES=16384u
FUZZ_BINS = $(FUZZ_TARGETS:%=$(BUILD)/fuzz/fuzz_%)
VALGRIND = valgrind -q --error-exitcode=99 --leak-check=full \
           --errors-for-leak-kinds=definite,indirect,possible \
           --trace-children=yes --trace-children-skip='*/gzip,*/cp,*/rm,*/mv' \
           --log-file=build/valgrind/memcheck.%p.log

FUZZ_SMOKE_SECONDS ?= 60
# Can $(FUZZ_CC) link a libFuzzer program (clang and its runtime)?
FUZZ_PROBE = printf 'int LLVMFuzzerTestOneInput(const char *d, unsigned long n);\n%s\n' \
  'int LLVMFuzzerTestOneInput(const char *d, unsigned long n) { return (int)(d && n) * 0; }' \
  | $(FUZZ_CC) -fsanitize=fuzzer -x c - -o $(BUILD)/fuzz/probe >/dev/null 2>&1
# Target $$t for $(1) seconds (an argument of $(call)): seeds from
# tests/corpus/$$t, new inputs to $(BUILD)/fuzz/corpus/$$t, a failing
# input to $(BUILD)/fuzz/crash-$$t-*.
FUZZ_RUN = ./$(BUILD)/fuzz/fuzz_$$t -max_total_time=$(1) -timeout=10 -print_final_stats=1 \
    -artifact_prefix=$(BUILD)/fuzz/crash-$$t- \
    $$(test -f tests/fuzz/$$t.dict && echo -dict=tests/fuzz/$$t.dict) \
    $(BUILD)/fuzz/corpus/$$t tests/corpus/$$t
.PHONY: valgrind fuzz fuzz-replay fuzz-smoke
$(TEST_BIN): $(BUILD)/tests/fuzz/targets.o
$(BUILD)/tests/fuzz/targets.o $(BUILD)/tests/fuzz/replay.o: tests/fuzz/targets.h | $(BUILD)/tests/fuzz
$(BUILD)/tests/fuzz:
	$(Q)mkdir -p $@

$(BUILD)/tests/fuzz/replay: $(BUILD)/tests/fuzz/replay.o $(BUILD)/tests/fuzz/targets.o $(BUILD)/examples/lib/pbrt.o $(BUILD)/examples/lib/count.o $(BUILD)/examples/lib/loopsubdiv.o $(TEST_LIB)
	$(SAY) LINK $@
	$(Q)$(CC) $(CFLAGS) $^ -o $@ $(LDLIBS)

fuzz-replay: $(BUILD)/tests/fuzz/replay
	$(Q)for t in $(FUZZ_TARGETS); do ./$(BUILD)/tests/fuzz/replay $$t tests/corpus/$$t || exit 1; done

$(BUILD)/fuzz/fuzz_%: tests/fuzz/fuzz_%.c tests/fuzz/targets.c tests/fuzz/targets.h examples/lib/pbrt.c examples/lib/pbrt.h examples/lib/count.c examples/lib/count.h examples/lib/loopsubdiv.c examples/lib/loopsubdiv.h $(LIB_SRC) batchrt.h internal.h testing.h
	$(SAY) FUZZ $@
	$(Q)mkdir -p $(BUILD)/fuzz/corpus/$*
	$(Q)$(FUZZ_CC) $(FUZZ_FLAGS) -pthread -I. $(LIB_SRC) examples/lib/pbrt.c examples/lib/count.c examples/lib/loopsubdiv.c tests/fuzz/targets.c $< -o $@ -lm

fuzz: $(FUZZ_BINS)
	$(Q)for t in $(FUZZ_TARGETS); do $(call FUZZ_RUN,$(FUZZ_SECONDS)) || exit 1; done

# The log of each run goes to $(BUILD)/fuzz/smoke-NAME.log; when a run
# fails, its lines naming the problem and the input are shown.
fuzz-smoke:
	$(Q)mkdir -p $(BUILD)/fuzz
	$(Q)$(FUZZ_PROBE) || { echo "SKIP fuzz smoke: $(FUZZ_CC) cannot build libFuzzer programs"; exit 0; }; \
	$(MAKE) --no-print-directory $(FUZZ_BINS) || exit 1; \
	for t in $(FUZZ_TARGETS); do log=$(BUILD)/fuzz/smoke-$$t.log; \
	  if $(call FUZZ_RUN,$(FUZZ_SMOKE_SECONDS)) >$$log 2>&1; then \
	    echo "fuzz smoke $$t: $$(sed -n 's/^stat::number_of_executed_units: *//p' $$log) runs" \
	      "in $(FUZZ_SMOKE_SECONDS) s, no problem"; \
	  else grep -E '^fuzz target|ERROR|SUMMARY|Test unit written' $$log; echo "fuzz smoke $$t: FAILED (log: $$log)"; exit 1; fi; \
	done

# Children (the programs run by the CLI tests) log to their own files; a
# memcheck error in one makes it exit 99, which its test reports.
valgrind:
	$(MAKE) all build/valgrind/run_tests BUILD=build/valgrind OPT="-O1 -g"
	$(Q)rm -f build/valgrind/memcheck.*.log
	$(Q)BRT_BUILD=build/valgrind $(VALGRIND) ./build/valgrind/run_tests $(T); status=$$?; \
	  if grep -l "ERROR SUMMARY: [1-9]" build/valgrind/memcheck.*.log; then exit 1; fi; \
	  exit $$status
# == END HARDENING ========================================================

# == RENDER (demo, figures) ===============================================
# demo: the README's "run" command.  The instanced landscape (15 M
# instanced triangles), out of core at 60 % of its geometry bytes (the
# paper's range), batching points of at most 2 M instanced triangles,
# without and with proxies (and direct, the reference): one table, the
# image and the two heatmaps in $(BUILD)/demo.
# Its loads read cold (--drop-os-cache) from a disk modelled at 100 MiB/s
# (--disk-speed), so that the table shows what proxies save in time.
# figures: the paper's Figs. 1-3 and Fig. 4, inner proxies (PNG, CSV, SVG) in $(BUILD)/fig.
# bench-render: the instanced landscape and island at scale 200, 16 spp at
# 640x360, proxies off and on, at 60 % of the geometry bytes (read cold, and
# from a modelled 100 MiB/s disk) and in core.
.PHONY: demo figures bench-render
DEMO_DISK = --drop-os-cache --disk-speed 100M
demo: all
	mkdir -p $(BUILD)/demo
	@echo "demo: the disk is modelled: every load reads the scene file cold (--drop-os-cache, the OS"
	@echo "      cache is told to drop it) and lasts at least its bytes / 100 MiB/s (--disk-speed 100M,"
	@echo "      about a hard disk; the rest of a faster read is slept)"
	./$(BUILD)/render landscape --scale 2 --point-tris 50000 --point-instanced 2000000 --memory 60% \
	  --rays-in-flight 32768 --compare \
	  $(DEMO_DISK) --out $(BUILD)/demo/landscape.png --heatmap $(BUILD)/demo/heatmap.png \
	  --stats $(BUILD)/demo/stats.json

figures: all
	./$(BUILD)/figures --out $(BUILD)/fig

# bench-paper: Fig. 3 in the paper's regime (issue 28): the instanced
# landscape and island, batching points of at most PAPER_INSTANCED instanced
# triangles, 128^3 proxies, limits 60-90 % of the geometry bytes (unique
# blobs plus instance tables), both schedulers, the paper's ratios beside
# them; a Markdown table on stdout, the CSV in $(BUILD)/paper.
PAPER_SCALE ?= 20
PAPER_INSTANCED ?= 20000000
.PHONY: bench-paper
bench-paper: all
	./$(BUILD)/figures --paper --out $(BUILD)/paper --scale $(PAPER_SCALE) --point-tris 200000 \
	  --point-instanced $(PAPER_INSTANCED)

# bench-order: the bottom level of the batched mode (build/bench_order,
# linked with $(TEST_LIB) for its counters): the instanced landscape and
# island at ORDER_SCALE and the mesh ORDER_MESH (gunzipped into
# ORDER_BENCH; SKIP rows without it), ORDER_RAYS camera and ORDER_RAYS
# diffuse rays each, one thread, in core (the paper's scheduler) and out
# of core (30 % of the geometry bytes): BVH nodes per batched ray and the
# batches' Mrays/s with layer 10's clip and layer 11's order off and on,
# ORDER_REPEAT rounds; then proxies off against --proxies-in-core without
# a limit.  Two Markdown tables; scene files built once in ORDER_BENCH.
# Every run's hits are held byte-equal (exit 1 if not); figures only.
ORDER_SCALE  ?= 80
ORDER_RAYS   ?= 400000
ORDER_REPEAT ?= 3
ORDER_MESH   ?= ../shared/data/meshes/dragon.obj.gz
ORDER_BENCH  ?= /tmp/batchrt-bench-order
.PHONY: bench-order
bench-order: all
	./$(BUILD)/bench_order --scale $(ORDER_SCALE) --rays $(ORDER_RAYS) --repeat $(ORDER_REPEAT) \
	  --mesh $(ORDER_MESH) --dir $(ORDER_BENCH)

BENCH_RENDER = --scale 200 --point-tris 100000 --point-instanced 20000000 --spp 16 --width 640 \
  --height 360 --compare
bench-render: all
	for scene in landscape island; do \
	  ./$(BUILD)/render $$scene $(BENCH_RENDER) --memory 60% --drop-os-cache \
	    --out $(BUILD)/bench-render-$$scene.png || exit 1; \
	  ./$(BUILD)/render $$scene $(BENCH_RENDER) --memory 60% --disk-speed 100M \
	    --out $(BUILD)/bench-render-$$scene.png || exit 1; \
	  ./$(BUILD)/render $$scene $(BENCH_RENDER) --out $(BUILD)/bench-render-$$scene.png || exit 1; \
	done
# bench-inner: inner proxies (README "Inner proxies"): the crown and the
# island at scale 10 (the crown closed, the island's land masses closed; the
# instances have no inner proxies), 25 % of the geometry bytes, next-event estimation,
# outer proxies alone (--no-inner) against outer + inner; one JSON each in
# $(BUILD)/inner, a Markdown table of the counts, and the two images compared.
BENCH_INNER = --scale 10 --point-tris 30000 --point-instanced 2000000 --spp 4 --width 320 --height 180 --memory 25%
.PHONY: bench-inner
bench-inner: all
	@mkdir -p $(BUILD)/inner
	@echo "| scene | proxies | disk MiB | loads | occluded shadow rays | settled by inner proxies | pool KB |"
	@echo "|---|---|---:|---:|---:|---:|---:|"
	@for scene in crown island; do \
	  for run in outer inner; do \
	    j=$(BUILD)/inner/$$scene-$$run.json; \
	    ./$(BUILD)/render $$scene $(BENCH_INNER) $$( [ $$run = outer ] && echo --no-inner ) \
	      --out $(BUILD)/inner/$$scene-$$run.png --stats $$j > /dev/null 2>&1 || exit 1; \
	    awk -v scene=$$scene -v run=$$run -F'[:,]' '{ gsub(/[ "]/, "", $$1); v[$$1] = $$2 } END { \
	      printf "| %s | %s | %.1f | %d | %d | %s | %.0f |\n", scene, run == "outer" ? "outer" : "outer + inner", \
	        v["disk_bytes_read"] / 1048576, v["batch_loads"], v["occlusion_hits"], \
	        run == "outer" ? "-" : sprintf("%d (%.1f %%)", v["occlusion_inner_stopped"], \
	          100 * v["occlusion_inner_stopped"] / v["occlusion_hits"]), v["proxy_bytes"] / 1000 }' $$j; \
	  done; \
	  cmp $(BUILD)/inner/$$scene-outer.png $(BUILD)/inner/$$scene-inner.png || exit 1; \
	done
# == END RENDER ===========================================================

# == THREADS (speed-ups; not part of CI) =================================
# bench-threads: each of the README's four targets (section "Threads") at
# 1 and THREADS_N threads, THREADS_REPEAT times each: trace --direct (1M
# bounce rays on the shared dragon), render in core and at 25 % with
# --disk-speed 100M (landscape --scale 10, 320x180, 8 spp), and the scene
# build (the landscape at --scale 10 from the generator).  Prints the
# timed part's wall seconds (from --stats) and the process's CPU seconds;
# checks that every statistics count is equal across the thread counts.
# The in-core and 25 % runs have scene files of their own: the default
# point size follows the memory limit (README, "The default point size").
THREADS_N      ?= 2
THREADS_REPEAT ?= 3
THREADS_DIR    ?= /tmp/batchrt-bench-threads
.PHONY: bench-threads
bench-threads: all
	@set -e; d=$(THREADS_DIR); b=./$(BUILD); mkdir -p $$d; \
	num() { sed -n "s/.*\"$$2\": *\([0-9.eE+-]*\).*/\1/p" $$1; }; \
	counts() { grep -v 'seconds\|mrays\|peak_rss' $$1; }; \
	m=$$d/dragon.obj; test -s $$m || gzip -dc ../shared/data/meshes/dragon.obj.gz > $$m; \
	$$b/raygen $$m $$d/rays --kind bounce --count 1000000 --seed 1 > /dev/null; \
	land="landscape --scale 10"; \
	img="--width 320 --height 180 --spp 8"; \
	$$b/render $$land --width 1 --height 1 --spp 1 --scene $$d/land.brs --out $$d/x.png > /dev/null; \
	$$b/render $$land --width 1 --height 1 --spp 1 --scene $$d/land25.brs --memory 25% --out $$d/x.png > /dev/null; \
	run() { name=$$1; field=$$2; shift 2; \
	  for t in 1 $(THREADS_N); do for i in $$(seq $(THREADS_REPEAT)); do \
	    rm -f $$d/build.brs; \
	    /usr/bin/time -f "%U %S" -o $$d/cpu "$$@" --threads $$t --stats $$d/s$$t.json > /dev/null; \
	    awk -v n="$$name" -v t=$$t -v w=$$(num $$d/s$$t.json $$field) \
	      -v l=$$(num $$d/s$$t.json load_seconds) -v c="$$(cat $$d/cpu)" \
	      'BEGIN { split(c, u, " "); printf "| %s | %d | %.2f | %.2f | %.2f |\n", \
	        n, t, w, u[1] + u[2], l }'; \
	  done; done; \
	  counts $$d/s1.json > $$d/c1; counts $$d/s$(THREADS_N).json > $$d/c2; \
	  cmp -s $$d/c1 $$d/c2 && echo "| (counts equal) | | | | |" || echo "| COUNTS DIFFER | | | | |"; }; \
	echo "| run | threads | wall s (timed part) | CPU s (process) | loads s |"; echo "|---|---:|---:|---:|---:|"; \
	run "trace --direct" seconds $$b/trace $$m $$d/rays $$d/hits --direct; \
	run "render in core" seconds $$b/render $$land $$img --scene $$d/land.brs --out $$d/x.png; \
	run "render 25%, --disk-speed 100M" seconds $$b/render $$land $$img --scene $$d/land25.brs \
	  --memory 25% --disk-speed 100M --out $$d/x.png; \
	run "scene build" build_seconds $$b/render $$land --width 1 --height 1 --spp 1 \
	  --scene $$d/build.brs --out $$d/x.png
# == END THREADS ==========================================================

# == SCALE (out of core from end to end; not part of CI) ==================
# bench-scale: an OBJ of the crown, SCALE_OBJ * 100K triangles, written by mkscene and
# its scene file built by trace --batched (a mesh file: the build holds its
# vertex positions), the instanced landscape at SCALE_LAND (285: the
# paper's 26 M unique triangles, 5.9 G instanced) whose scene file render
# builds straight from its streams, then a render of that landscape at
# 640x360, 16 spp, --memory SCALE_MEMORY.  Prints time, disk and peak RSS
# of each step and checks the README's two statements ("Memory"): a build
# peaks at no more than build_bound (below: 256 MiB, the vertices, the DAG,
# the prototypes' BVHs and the points in the works); a render at no more than
# its limit + 280 B per path in flight + 512 B per batching point + 40 B
# per pixel + 16 MiB.  Exit status 1 when a statement fails.  The files
# (the scene files and the OBJ) go to SCALE_DIR and
# are removed at the end unless SCALE_KEEP=1.
SCALE_LAND   ?= 285
SCALE_INSTANCED ?= 20000000
SCALE_OBJ    ?= 200
SCALE_MEMORY ?= 1G
SCALE_BATCH  ?= 100000
SCALE_DIR    ?= /tmp/batchrt-bench-scale
SCALE_KEEP   ?= 0
# The shell functions of bench-scale and bench-island: num FILE FIELD (a
# statistics number), mib BYTES, cpu OUT CMD... (user and system seconds of
# CMD into OUT), speed TRIANGLES SECONDS CPUFILE, check WHAT PEAK BOUND (a
# memory statement: prints it, sets fail=1 when it is violated), and
# build_bound DAG VERTICES PROTOTYPE_TRIANGLES POINT_TRIS READ: the README's
# statement of a build (256 MiB, 12 B per vertex of an indexed input, the
# DAG, 64 B per prototype triangle, 256 B per triangle of a point for each
# build thread, one per core), plus READ, what the one-pixel render after
# it read with no limit; largest_blob SCENE (the largest blob of a scene
# file, from its point table) and render_bound JSON PIXELS SCENE: the
# README's statement of a render (its limit, 280 B per path in flight, 512
# B per point, 40 B per pixel, 16 MiB, and with threads the largest blob
# read ahead and 1 MiB per thread, one per core).
BENCH_SCALE_SH = \
	num() { sed -n "s/.*\"$$2\": *\([0-9.eE+-]*\).*/\1/p" $$1; }; \
	mib() { awk -v x=$$1 'BEGIN { printf "%.1f MiB", x / 1048576 }'; }; \
	cpu() { out=$$1; shift; if [ -x /usr/bin/time ]; then /usr/bin/time -f "%U %S" -o $$out "$$@"; \
	  else "$$@"; echo "0 0" > $$out; fi; }; \
	speed() { awk -v t=$$1 -v s=$$2 -v c="$$(cat $$3)" 'BEGIN { split(c, u, " "); \
	  printf "build %.1f s wall (%.2f M triangles/s), %.1f s CPU (%.2f M triangles/s)", \
	    s, t / s / 1e6, u[1] + u[2], t / (u[1] + u[2] + 1e-9) / 1e6 }'; }; \
	check() { if awk -v what="$$1" -v peak=$$2 -v bound=$$3 'BEGIN { \
	  printf "  %s: peak RSS %.1f MiB <= bound %.1f MiB: %s\n", what, peak / 1048576, \
	    bound / 1048576, peak <= bound ? "holds" : "VIOLATED"; exit peak > bound }'; \
	  then return 0; else fail=1; return 1; fi; }; \
	build_bound() { awk -v dag=$$1 -v v=$$2 -v p=$$3 -v pt=$$4 -v read=$$5 \
	  -v thr=$$(getconf _NPROCESSORS_ONLN) 'BEGIN { printf "%.0f", \
	    256 * 1048576 + 12 * v + dag + 64 * p + thr * 256 * pt + read }'; }; \
	largest_blob() { v=$$(od -An -t u4 -j 8 -N 4 $$1 | tr -d ' '); \
	  n=$$(od -An -t u4 -j 32 -N 4 $$1 | tr -d ' '); at=$$(od -An -t u8 -j 56 -N 8 $$1 | tr -d ' '); \
	  e=$$([ "$$v" = 4 ] && echo 104 || echo 80); \
	  od -An -v -t u8 -w$$e -j $$at -N $$((n * e)) $$1 | awk 'BEGIN { m = 0 } $$5 > m { m = $$5 } END { print m }'; }; \
	render_bound() { awk -v l=$$(num $$1 memory_limit) -v p=$$(num $$1 paths_in_flight) \
	  -v n=$$(num $$1 batching_points) -v px=$$2 -v blob=$$(largest_blob $$3) \
	  -v thr=$$(getconf _NPROCESSORS_ONLN) 'BEGIN { printf "%.0f", l + 280 * p + 512 * n + 40 * px \
	    + 16 * 1048576 + (thr > 1 ? blob + thr * 1048576 : 0) }'; };
.PHONY: bench-scale
bench-scale: all
	@set -e; d=$(SCALE_DIR); b=./$(BUILD); mkdir -p $$d; $(BENCH_SCALE_SH) \
	fail=0; df -h $$d | tail -1; \
	head -c 32 /dev/zero > $$d/one.rays; \
	echo "== mkscene crown --scale $(SCALE_OBJ) big.obj"; \
	$$b/mkscene crown $$d/big.obj --scale $(SCALE_OBJ) | tee $$d/mkscene.txt; \
	tris=$$(sed -n 's/^crown: \([0-9]*\) triangles.*/\1/p' $$d/mkscene.txt); \
	verts=$$(sed -n 's/.* \([0-9]*\) vertices.*/\1/p' $$d/mkscene.txt); \
	echo "  file $$(stat -c %s $$d/big.obj) bytes"; \
	echo "== trace big.obj --batched: the scene file from the OBJ"; rm -f $$d/obj.brs; \
	cpu $$d/obj.cpu $$b/trace $$d/big.obj $$d/one.rays $$d/one.hits --batched --point-tris $(SCALE_BATCH) \
	  --scene $$d/obj.brs --stats $$d/obj.json; \
	echo "  $$tris triangles, $$verts vertices: $$(speed $$tris $$(num $$d/obj.json build_seconds) $$d/obj.cpu),"\
	  "scene file $$(stat -c %s $$d/obj.brs) bytes"; \
	check "build from the OBJ" $$(num $$d/obj.json peak_rss_bytes) $$(build_bound \
	  $$(num $$d/obj.json proxy_bytes) $$verts 0 $(SCALE_BATCH) $$(num $$d/obj.json disk_bytes_read)) || :; \
	rm -f $$d/big.obj $$d/obj.brs; \
	echo "== render landscape --scale $(SCALE_LAND): the scene file from the instanced scene's streams"; \
	rm -f $$d/land.brs; \
	cpu $$d/land.cpu $$b/render landscape --scale $(SCALE_LAND) --point-tris $(SCALE_BATCH) \
	  --point-instanced $(SCALE_INSTANCED) --width 1 --height 1 \
	  --spp 1 --scene $$d/land.brs \
	  --out $$d/one.png --stats $$d/land-build.json | tee $$d/land.txt; \
	tris=$$(sed -n 's/^landscape: \([0-9]*\) unique.*/\1/p' $$d/land.txt); \
	proto=$$(sed -n 's/.*(\([0-9]*\) in prototypes).*/\1/p' $$d/land.txt); \
	echo "  $$tris unique triangles: $$(speed $$tris $$(num $$d/land-build.json build_seconds) $$d/land.cpu),"\
	  "scene file $$(stat -c %s $$d/land.brs) bytes"; \
	check "build from the generator" $$(num $$d/land-build.json peak_rss_bytes) $$(build_bound \
	  $$(num $$d/land-build.json proxy_bytes) 0 $$proto $(SCALE_BATCH) \
	  $$(num $$d/land-build.json disk_bytes_read)) || :; \
	echo "== render landscape --scale $(SCALE_LAND) 640x360, 16 spp, --memory $(SCALE_MEMORY)"; \
	render="$$b/render landscape --scale $(SCALE_LAND) --point-tris $(SCALE_BATCH) \
	  --point-instanced $(SCALE_INSTANCED) --width 640 \
	  --height 360 --spp 16 --memory $(SCALE_MEMORY) --scene $$d/land.brs --out $$d/land.png"; \
	$$render --stats $$d/render.json; \
	j=$$d/render.json; \
	echo "  $$(awk -v s=$$(num $$j seconds) 'BEGIN { printf "%.1f", s }') s, read $$(mib $$(num $$j disk_bytes_read)) in $$(num $$j batch_loads) loads,"\
	  "$$(num $$j batching_points) batching points, DAG $$(mib $$(num $$j proxy_bytes)),"\
	  "$$(num $$j paths_in_flight) paths in flight"; \
	check "render" $$(num $$j peak_rss_bytes) $$(render_bound $$j $$((640 * 360)) $$d/land.brs) || :; \
	if [ "$(SCALE_KEEP)" != 1 ]; then rm -f $$d/land.brs; fi; \
	exit $$fail
# == END SCALE ============================================================

# == ISLAND (the paper's largest scene; not part of CI; about an hour) ====
# bench-island: the instanced island at ISLAND_SCALE (1900: about 156 M unique
# and 31 G instanced triangles, the paper's Table 1: 143 M and 31 G), in
# points of at most ISLAND_TRIS unique and ISLAND_INSTANCED instanced
# triangles (about the paper's 1,984 points), its scene file built by render
# straight from the streams; a render at ISLAND_MEMORY (320x180, 4 spp), each
# step's time and peak RSS checked against the README's statements as in
# bench-scale; then one point of Fig. 3 in bench-paper's regime (the
# paper's scheduler, 60 %, 160x90, 4 spp, grey, no shadow rays): disk
# bytes with proxies over without.  Files in ISLAND_DIR, removed at the end
# unless SCALE_KEEP=1; with SCALE_KEEP=1 a kept scene file is reused, the
# build and its check skipped.
ISLAND_SCALE     ?= 1900
ISLAND_TRIS      ?= 2000000
ISLAND_INSTANCED ?= 16000000
ISLAND_MEMORY    ?= 1G
ISLAND_DIR       ?= /tmp/batchrt-bench-island
.PHONY: bench-island
bench-island: all
	@set -e; d=$(ISLAND_DIR); b=./$(BUILD); mkdir -p $$d; $(BENCH_SCALE_SH) \
	fail=0; df -h $$d | tail -1; \
	scene="island --scale $(ISLAND_SCALE) --point-tris $(ISLAND_TRIS) \
	  --point-instanced $(ISLAND_INSTANCED) --scene $$d/island.brs"; \
	if [ "$(SCALE_KEEP)" = 1 ] && [ -f $$d/island.brs ]; then \
	  echo "== $$d/island.brs kept by SCALE_KEEP=1: no build (render rebuilds a stale one)"; \
	else \
	echo "== render $$scene: the scene file from the streams"; rm -f $$d/island.brs; \
	cpu $$d/island.cpu $$b/render $$scene --width 1 --height 1 --spp 1 --out $$d/one.png \
	  --stats $$d/build.json | tee $$d/island.txt; \
	proto=$$(sed -n 's/.*(\([0-9]*\) in prototypes).*/\1/p' $$d/island.txt); \
	tris=$$(sed -n 's/^island: \([0-9]*\) unique.*/\1/p' $$d/island.txt); \
	echo "  $$tris unique triangles: $$(speed $$tris $$(num $$d/build.json build_seconds) $$d/island.cpu),"\
	  "scene file $$(stat -c %s $$d/island.brs) bytes"; \
	check "build from the generator" $$(num $$d/build.json peak_rss_bytes) $$(build_bound \
	  $$(num $$d/build.json proxy_bytes) 0 $$proto $(ISLAND_TRIS) $$(num $$d/build.json disk_bytes_read)) || :; \
	fi; \
	echo "== render $$scene 320x180, 4 spp, --memory $(ISLAND_MEMORY)"; \
	$$b/render $$scene --width 320 --height 180 --spp 4 --memory $(ISLAND_MEMORY) --out $$d/island.png \
	  --stats $$d/render.json; \
	j=$$d/render.json; \
	echo "  $$(awk -v s=$$(num $$j seconds) 'BEGIN { printf "%.1f", s }') s, read"\
	  "$$(mib $$(num $$j disk_bytes_read)) in $$(num $$j batch_loads) loads, $$(num $$j batching_points)"\
	  "batching points, DAG $$(mib $$(num $$j proxy_bytes))"; \
	check "render" $$(num $$j peak_rss_bytes) $$(render_bound $$j $$((320 * 180)) $$d/island.brs) || :; \
	for proxies in --no-proxy ""; do \
	  $$b/render $$scene --paper-scheduler --grey --no-nee --width 160 --height 90 --spp 4 --memory 60% \
	    $$proxies --out $$d/fig3.png --stats $$d/fig3$$proxies.json > /dev/null; \
	done; \
	awk -v n=$$(num $$d/fig3--no-proxy.json disk_bytes_read) -v p=$$(num $$d/fig3.json disk_bytes_read) \
	  'BEGIN { printf "  Fig. 3 at 60 %%, the paper'"'"'s scheduler: %.1f GiB without proxies, %.1f GiB with: %.2f\n", \
	    n / 1073741824, p / 1073741824, p / n }'; \
	if [ "$(SCALE_KEEP)" != 1 ]; then rm -f $$d/island.brs; fi; \
	exit $$fail
# == END ISLAND ===========================================================

# == INSTALL ==============================================================
#   make install       $(LIB), batchrt.h and a pkg-config file batchrt.pc
#                      into $(DESTDIR)$(LIBDIR), $(DESTDIR)$(INCLUDEDIR) and
#                      $(DESTDIR)$(PKGCONFIGDIR); PREFIX defaults to /usr/local,
#                      DESTDIR (staging) never appears in batchrt.pc
#   make uninstall     removes those three files (same PREFIX and DESTDIR)
#   make install-check installs into $(BUILD)/install-check/prefix, builds
#                      examples/tutorials/minimal_batched.c from a copy beside it (so
#                      no header of the tree can be found) with the flags of
#                      "pkg-config --cflags --libs batchrt", runs it, requires
#                      the output of $(BUILD)/minimal_batched, checks that
#                      DESTDIR stages and uninstall removes, and removes the
#                      folder.  Under a second; "make test" runs it.
# Only the static library is installed, so batchrt.pc lists its own
# libraries (-lm -pthread) under Libs, not Libs.private: a static link
# needs them and "pkg-config --libs" without --static leaves private ones out.
PREFIX       ?= /usr/local
LIBDIR       ?= $(PREFIX)/lib
INCLUDEDIR   ?= $(PREFIX)/include
PKGCONFIGDIR ?= $(LIBDIR)/pkgconfig
PKG_CONFIG   ?= pkg-config
BRT_VERSION   = 0.1
define PC_FILE
prefix=$(PREFIX)
libdir=$(patsubst $(PREFIX)/%,$${prefix}/%,$(LIBDIR))
includedir=$(patsubst $(PREFIX)/%,$${prefix}/%,$(INCLUDEDIR))

Name: batchrt
Description: conservative ray batching with geometry proxies (Molenaar and Eisemann 2020), C99 reference
Version: $(BRT_VERSION)
Cflags: -I$${includedir}
Libs: -L$${libdir} -lbatchrt -lm -pthread
endef
export PC_FILE
INSTALLED = $(DESTDIR)$(LIBDIR)/libbatchrt.a $(DESTDIR)$(INCLUDEDIR)/batchrt.h \
            $(DESTDIR)$(PKGCONFIGDIR)/batchrt.pc
.PHONY: install uninstall install-check
install: $(LIB)
	$(SAY) INSTALL "$(DESTDIR)$(PREFIX)"
	$(Q)install -d "$(DESTDIR)$(LIBDIR)" "$(DESTDIR)$(INCLUDEDIR)" "$(DESTDIR)$(PKGCONFIGDIR)"
	$(Q)install -m 644 $(LIB) "$(DESTDIR)$(LIBDIR)/libbatchrt.a"
	$(Q)install -m 644 batchrt.h "$(DESTDIR)$(INCLUDEDIR)/batchrt.h"
	$(Q)printf '%s\n' "$$PC_FILE" > "$(DESTDIR)$(PKGCONFIGDIR)/batchrt.pc"

uninstall:
	$(SAY) REMOVE "$(DESTDIR)$(PREFIX)"
	$(Q)rm -f $(INSTALLED:%="%")

# Without pkg-config the flags are read from batchrt.pc itself: its variable
# lines (name=value, ${name} references) are shell assignments, so eval
# expands them as pkg-config would; a line says so.  The lines that run
# $(MAKE) are separate so that "make -n install-check" only prints.
INSTALL_CHECK = $(abspath $(BUILD))/install-check
install-check: $(LIB) $(BUILD)/minimal_batched
	$(SAY) CHECK "make install, pkg-config, $(INSTALL_CHECK)"
	$(Q)rm -rf "$(INSTALL_CHECK)" && mkdir -p "$(INSTALL_CHECK)"
	$(Q)$(MAKE) --no-print-directory -s install PREFIX="$(INSTALL_CHECK)/prefix" DESTDIR=
	$(Q)set -e; d="$(INSTALL_CHECK)"; pc="$$d/prefix/lib/pkgconfig/batchrt.pc"; \
	if command -v $(PKG_CONFIG) >/dev/null 2>&1; then \
	  flags=$$(PKG_CONFIG_PATH="$$d/prefix/lib/pkgconfig" $(PKG_CONFIG) --cflags --libs batchrt); \
	else echo "install-check: no $(PKG_CONFIG); the flags are read from batchrt.pc with sed"; \
	  eval "$$(sed -n 's/^\([a-z]*\)=\(.*\)$$/\1="\2"/p' "$$pc")"; \
	  flags=$$(eval echo "$$(sed -n 's/^Cflags: //p; s/^Libs: //p' "$$pc" | tr '\n' ' ')"); fi; \
	cp examples/tutorials/minimal_batched.c "$$d/"; \
	$(CC) $(CFLAGS) "$$d/minimal_batched.c" $$flags -o "$$d/minimal_batched"; \
	TMPDIR="$$d" "$$d/minimal_batched" > "$$d/installed.out"; \
	TMPDIR="$$d" ./$(BUILD)/minimal_batched > "$$d/tree.out"; \
	cmp -s "$$d/installed.out" "$$d/tree.out" || { echo "install-check: the installed copy printed"; \
	  cat "$$d/installed.out"; exit 1; }
	$(Q)$(MAKE) --no-print-directory -s install DESTDIR="$(INSTALL_CHECK)/stage" PREFIX=/opt/batchrt
	$(Q)grep -qx 'prefix=/opt/batchrt' "$(INSTALL_CHECK)/stage/opt/batchrt/lib/pkgconfig/batchrt.pc" && \
	test -f "$(INSTALL_CHECK)/stage/opt/batchrt/lib/libbatchrt.a" && \
	test -f "$(INSTALL_CHECK)/stage/opt/batchrt/include/batchrt.h"
	$(Q)$(MAKE) --no-print-directory -s uninstall DESTDIR="$(INSTALL_CHECK)/stage" PREFIX=/opt/batchrt
	$(Q)left=$$(find "$(INSTALL_CHECK)/stage" -type f); \
	test -z "$$left" || { echo "install-check: uninstall left $$left"; exit 1; }; \
	rm -rf "$(INSTALL_CHECK)"
# == END INSTALL ==========================================================

clean:
	rm -rf build

.SECONDARY:
