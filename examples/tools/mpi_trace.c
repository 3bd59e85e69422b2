/*
** examples/tools/mpi_trace.c -- trace's batched mode spread over MPI ranks:
** batching points owned by ranks, rays forwarded between them, and the
** proxies deciding which rays cross the network (README, "Beyond one
** machine").  Optional, like Embree: built by "make mpi" when mpicc exists.
**
**   mpirun -np 4 build/mpi_trace SCENE RAYS HITS [options]
**
** The method is the library's layer 6 (batchrt.h, "Beyond one process"):
** each rank opens the scene file, so it holds the top-level BVH and every
** proxy, and owns the batching points brt_scene_assign gives it -- runs of
** the top-level leaf order balanced by bytes (--assign round-robin: the
** alternative) -- whose blobs alone it reads, under its own --memory.
** Each rank starts its share of the rays (a contiguous range of the ray
** file).  A walk that stops at a point another rank owns sends the ray
** there with its state (brt_ray_state: 88 bytes); a ray finishes wherever
** its walk ends, and rank 0 gathers the hits in ray order and writes the
** file, byte for byte what "trace --direct" writes, at any number of ranks.
**
** THE NETWORK, in four parts:
**   outboxes  rays for rank k gather in outbox k; a full outbox, and every
**             outbox whenever the library asks for rays (after each batch
**             and when idle), is sent with MPI_Isend: one message carries
**             what one batch sent there, at most RAYS_PER_MESSAGE rays
**   inbox     messages probed and received without blocking (MPI_Iprobe)
**   the end   every ray finishes exactly once, somewhere, and the total is
**             known: each rank reports the rays it finished to rank 0 when
**             it runs idle; when rank 0's sum reaches the total, no ray is
**             queued or in flight anywhere, and rank 0 tells every rank so
**   the model --net-speed S makes each message last at least its bytes / S
**             (its sender sleeps), as --disk-speed S does each read
** Idle ranks poll (MPI_Iprobe and a short sleep) rather than block in
** MPI_Probe: Open MPI's blocking calls spin, which starves the other
** ranks when there are more ranks than cores (mpirun --oversubscribe).
**
** FAILURES.  Before the trace, the ranks agree on errors (opening the
** scene, reading the rays): the first failing rank prints one line and all
** exit 1.  During the trace a failing rank prints its line and calls
** MPI_Abort, which ends every rank; so does mpirun when a rank dies of a
** signal.  Only rank 0 writes, at the end, atomically: a failed run
** leaves no output file.  For the tests, BRT_MPI_FAIL=RANK:WHEN injects a
** failure on one rank: WHEN is "open" (its scene does not open), "send"
** (its first message fails) or "signal" (it is killed by SIGKILL at its
** first message).
*/
#include <mpi.h>

#include "common.h"
#include "input.h"
#include "tracer.h"

#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

static const char *const prog = "mpi_trace";

/* 4096 rays of 88 bytes: 352 KiB, long enough that a message's latency
** is small beside its transfer on a cluster network, short enough that a
** busy rank's rays leave while it works.  Results go to rank 0 in chunks
** of 2^20 (32 MiB).  Both may be set on the compiler's command line: the
** tests build a second binary (build/tests/mpi_trace_small) with chunks of
** 1000 results, so that a test crosses the split with a few thousand
** rays; make test-long runs the shipped value past 2^20. */
#ifndef RAYS_PER_MESSAGE
#define RAYS_PER_MESSAGE 4096
#endif
#ifndef RESULTS_PER_MESSAGE
#define RESULTS_PER_MESSAGE (1 << 20)
#endif

enum { TAG_RAYS = 1, TAG_FINISHED, TAG_DONE, TAG_RESULTS };

/* ---- options ------------------------------------------------------------ */

typedef struct options {
    ex_tracer_options t;             /* the options of every tracer (tracer.h) */
    uint64_t net_speed, disk_speed;  /* --net-speed, --disk-speed: bytes a second; 0: unmodelled */
    int round_robin;                 /* --assign round-robin */
} options;

static void usage(void)
{
    printf("usage: mpirun -np N build/mpi_trace SCENE RAYS HITS [options]\n"
           "Batched tracing over N MPI ranks: each rank owns some batching points and reads\n"
           "only their blobs; a ray whose walk stops at a point another rank owns is sent\n"
           "there.  SCENE is a scene file (.brs), or a mesh or .pbrt file whose scene file\n"
           "rank 0 builds (or reuses) first.  HITS is trace's hit file, byte for byte.\n"
           "\n"
           "  --occlusion       occlusion queries: HITS becomes an occlusion file\n"
           "  --memory SIZE     each rank's geometry-cache budget, e.g. 256M (default 1G)\n"
           "  --no-proxy        no voxel proxies: every batching point entered is a stop\n"
           "  --assign KIND     runs (default: runs of the top-level leaf order balanced\n"
           "                    by bytes) or round-robin (point k to rank k mod N)\n"
           "  --net-speed SIZE  model a network: each message lasts at least its bytes\n"
           "                    divided by SIZE per second, e.g. 1G (default: unmodelled)\n"
           "  --disk-speed SIZE model a slower disk: each read lasts at least its bytes\n"
           "                    divided by SIZE per second (as render's)\n"
           "  --point-tris N    triangles per batching point when building (default as\n"
           "                    trace's: the triangles / max(8, 4 / the --memory share\n"
           "                    of the blobs), at least 100000)\n"
           "  --proxy-res R     proxy resolution when building, 2..1024 (default 128)\n"
           "  --scene FILE      the scene file to build from a mesh (default as trace's)\n"
           "  --paper-scheduler the paper's scheduler on every rank\n"
           "  --no-clip, --no-order  as trace's: no proxy entry guides the bottom level\n"
           "  --proxies-in-core as trace's\n"
           "  --threads N       threads per rank (default 1)\n"
           "  --rays-in-flight N  rays each rank works on at once (default 262144); more\n"
           "                    wait in its inbox\n"
           "  --stats FILE      statistics JSON: totals and one object per rank\n"
           "  --verbose         the summary line even when stderr is not a terminal\n"
           "  --help            this text\n"
           "\n"
           "Exit status 0 on success, 1 on bad input or a failed rank (no file is written).\n");
}

/* mpi_trace's own options, beside every tracer's (ex_tracer_parse). */
static int own_option(void *user, int argc, char **argv, int *i)
{
    options *o = user;
    const char *a = argv[*i];
    if (strcmp(a, "--disk-speed") == 0)
        o->disk_speed = ex_parse_size(prog, a, ex_option_value(prog, argc, argv, i));
    else if (strcmp(a, "--net-speed") == 0)
        o->net_speed = ex_parse_size(prog, a, ex_option_value(prog, argc, argv, i));
    else if (strcmp(a, "--assign") == 0) {
        const char *v = ex_option_value(prog, argc, argv, i);
        if (strcmp(v, "runs") == 0) o->round_robin = 0;
        else if (strcmp(v, "round-robin") == 0) o->round_robin = 1;
        else ex_die(prog, "--assign: expected runs or round-robin, got '%s'", v);
    }
    else return 0;
    return 1;
}

static void parse_options(int argc, char **argv, options *o)
{
    ex_tracer_command c = {prog, "SCENE RAYS HITS", 1, (uint64_t)1 << 24, own_option, o};
    memset(o, 0, sizeof *o);
    ex_tracer_defaults(&o->t);
    o->t.threads = 1;
    o->t.rays_in_flight = (uint64_t)1 << 18;
    ex_tracer_parse(&c, argc, argv, &o->t);
}

/* ---- failures --------------------------------------------------------------- */

/* Every rank reads the same command line: only rank 0 says what is wrong
** with it (the others' stderr is closed meanwhile), and all exit 1. */
static void parse_options_once(int argc, char **argv, options *o, int rank)
{
    int saved = dup(2), null = open("/dev/null", O_WRONLY);
    if (rank != 0 && saved >= 0 && null >= 0) dup2(null, 2);
    parse_options(argc, argv, o);
    if (rank != 0 && saved >= 0) dup2(saved, 2);
    if (saved >= 0) close(saved);
    if (null >= 0) close(null);
}

static int my_rank, rank_count;

/* An exit without MPI_Finalize (ex_die anywhere) ends every rank: else the
** others would wait for this one forever. */
static void abort_others(void)
{
    int initialized = 0, finalized = 0;
    MPI_Initialized(&initialized);
    MPI_Finalized(&finalized);
    if (initialized && !finalized) MPI_Abort(MPI_COMM_WORLD, 1);
}

/* A rank's trace failed: its line, and the end of every rank.  SIGTERM
** is mpirun ending the job (after MPI_Abort, or a rank's death, which
** mpirun reports): the ranks end quietly with the shell's status.  Ctrl-C
** (SIGINT, through mpirun to every rank) is told once, by rank 0. */
static void trace_failed(brt_result r, const char *message)
{
    if (r == BRT_EINTR && (my_rank != 0 || ex_interrupted() == SIGTERM)) _exit(128 + ex_interrupted());
    if (r == BRT_EINTR) ex_die_interrupted(prog);
    fprintf(stderr, "%s: rank %d: %s\n", prog, my_rank, message);
    MPI_Abort(MPI_COMM_WORLD, 1);
}

/* The injected failure of BRT_MPI_FAIL=RANK:WHEN on this rank, if WHEN. */
static int injected(const char *when)
{
    const char *spec = getenv("BRT_MPI_FAIL"), *colon;
    if (!spec || !(colon = strchr(spec, ':'))) return 0;
    return atoi(spec) == my_rank && strcmp(colon + 1, when) == 0;
}

/* Every rank says whether it failed (message: its line); the first that
** did prints it, and all exit 1 together. */
static void agree(const char *message)
{
    int mine = message ? my_rank : rank_count, first;
    MPI_Allreduce(&mine, &first, 1, MPI_INT, MPI_MIN, MPI_COMM_WORLD);
    if (first == rank_count) return;
    if (first == my_rank) fprintf(stderr, "%s: rank %d: %s\n", prog, my_rank, message);
    MPI_Finalize();
    exit(1);
}

/* ---- the network ------------------------------------------------------------- */

typedef struct pending_send {
    MPI_Request request;
    void *data;
} pending_send;

typedef struct network {
    const uint32_t *owner;      /* per batching point */
    brt_ray_state **outbox;     /* per rank */
    size_t *outbox_count;
    pending_send *pending;
    size_t pending_count, pending_capacity;
    brt_ray_state *inbox;
    size_t inbox_head, inbox_count, inbox_capacity;
    uint64_t total;             /* rays of the whole run */
    uint64_t finished, reported;    /* finished here; reported to rank 0 */
    uint64_t finished_everywhere;   /* rank 0: all ranks' reports and its own */
    int done;
    double net_speed;
    /* statistics */
    uint64_t rays_sent, rays_received, messages_sent, bytes_sent, messages_received;
} network;

static void *must_grow(void *p, size_t *capacity, size_t need, size_t size)
{
    void *grown = brt_grow(p, capacity, need, size);
    if (!grown) ex_die(prog, "rank %d: out of memory in the network buffers", my_rank);
    return grown;
}

/* Modelled network (--net-speed): the message lasts bytes / speed. */
static void model_transfer(const network *n, size_t bytes)
{
    if (n->net_speed > 0) ex_sleep_until(brt_seconds() + (double)bytes / n->net_speed);
}

/* Sends data (malloc'd, freed once sent) without blocking. */
static void post(network *n, int to, int tag, void *data, size_t bytes)
{
    pending_send *p;
    n->pending = must_grow(n->pending, &n->pending_capacity, n->pending_count + 1, sizeof *n->pending);
    p = &n->pending[n->pending_count++];
    p->data = data;
    model_transfer(n, bytes);
    MPI_Isend(data, (int)bytes, MPI_BYTE, to, tag, MPI_COMM_WORLD, &p->request);
    n->messages_sent++;
    n->bytes_sent += bytes;
}

/* Frees the buffers of the sends that completed. */
static void sends_progress(network *n)
{
    size_t i = 0;
    while (i < n->pending_count) {
        int complete = 0;
        MPI_Test(&n->pending[i].request, &complete, MPI_STATUS_IGNORE);
        if (!complete) { i++; continue; }
        free(n->pending[i].data);
        n->pending[i] = n->pending[--n->pending_count];
    }
}

static void outbox_send(network *n, int to)
{
    size_t bytes = n->outbox_count[to] * sizeof(brt_ray_state);
    if (n->outbox_count[to] == 0) return;
    post(n, to, TAG_RAYS, n->outbox[to], bytes);
    n->rays_sent += n->outbox_count[to];
    n->outbox[to] = malloc(RAYS_PER_MESSAGE * sizeof(brt_ray_state));
    if (!n->outbox[to]) ex_die(prog, "rank %d: out of memory for an outbox", my_rank);
    n->outbox_count[to] = 0;
}

/* brt_exchange.send: into the owner's outbox, sent when full. */
static int net_send(void *user, const brt_ray_state *ray)
{
    network *n = user;
    int to = (int)n->owner[ray->key_point];
    if (injected("signal")) raise(SIGKILL);
    if (injected("send")) return -1;
    n->outbox[to][n->outbox_count[to]++] = *ray;
    if (n->outbox_count[to] == RAYS_PER_MESSAGE) outbox_send(n, to);
    return 0;
}

/* One message that has arrived (status from a probe). */
static void receive_message(network *n, const MPI_Status *status)
{
    int bytes;
    MPI_Get_count(status, MPI_BYTE, &bytes);
    n->messages_received++;
    if (status->MPI_TAG == TAG_RAYS) {
        size_t count = (size_t)bytes / sizeof(brt_ray_state);
        if (n->inbox_head > 0 && n->inbox_count == 0) n->inbox_head = 0;
        n->inbox = must_grow(n->inbox, &n->inbox_capacity, n->inbox_head + n->inbox_count + count,
                             sizeof *n->inbox);
        MPI_Recv(n->inbox + n->inbox_head + n->inbox_count, bytes, MPI_BYTE, status->MPI_SOURCE,
                 TAG_RAYS, MPI_COMM_WORLD, MPI_STATUS_IGNORE);
        n->inbox_count += count;
        n->rays_received += count;
    } else if (status->MPI_TAG == TAG_FINISHED) {
        uint64_t finished;
        MPI_Recv(&finished, 8, MPI_BYTE, status->MPI_SOURCE, TAG_FINISHED, MPI_COMM_WORLD,
                 MPI_STATUS_IGNORE);
        n->finished_everywhere += finished;
    } else {
        MPI_Recv(NULL, 0, MPI_BYTE, status->MPI_SOURCE, TAG_DONE, MPI_COMM_WORLD, MPI_STATUS_IGNORE);
        n->done = 1;
    }
}

/* Receives every message that has arrived; nonzero when there was one. */
static int poll_messages(network *n)
{
    int any = 0, flag = 1;
    MPI_Status status;
    while (flag) {
        MPI_Iprobe(MPI_ANY_SOURCE, MPI_ANY_TAG, MPI_COMM_WORLD, &flag, &status);
        if (flag) receive_message(n, &status);
        any |= flag;
    }
    return any;
}

/* Rank 0 ends the run once every ray has finished somewhere. */
static void end_when_all_finished(network *n)
{
    int k;
    if (my_rank != 0 || n->done || n->finished_everywhere + n->finished < n->total) return;
    for (k = 1; k < rank_count; k++) post(n, k, TAG_DONE, NULL, 0);
    n->done = 1;
}

/* An idle rank tells rank 0 how many rays it finished since it last did. */
static void report_finished(network *n)
{
    uint64_t *count;
    if (my_rank == 0 || n->finished == n->reported) return;
    count = malloc(sizeof *count);
    if (!count) ex_die(prog, "rank %d: out of memory", my_rank);
    *count = n->finished - n->reported;
    n->reported = n->finished;
    post(n, 0, TAG_FINISHED, count, sizeof *count);
}

/* brt_exchange.receive: send the outboxes, then hand out what has arrived;
** when idle, wait (polling) for rays or for the end of the run. */
static size_t net_receive(void *user, brt_ray_state *rays, size_t max, int idle)
{
    network *n = user;
    struct timespec nap = {0, 100000};   /* 0.1 ms */
    size_t k;
    int to;
    for (to = 0; to < rank_count; to++) outbox_send(n, to);
    if (idle) report_finished(n);
    for (;;) {
        sends_progress(n);
        poll_messages(n);
        end_when_all_finished(n);
        if (n->inbox_count > 0 || !idle || n->done) break;
        if (ex_interrupted()) trace_failed(BRT_EINTR, NULL);
        nanosleep(&nap, NULL);
    }
    for (k = 0; k < max && n->inbox_count > 0; k++, n->inbox_count--) rays[k] = n->inbox[n->inbox_head++];
    return k;
}

static void network_init(network *n, const uint32_t *owner, uint64_t total, uint64_t net_speed)
{
    int k;
    memset(n, 0, sizeof *n);
    n->owner = owner;
    n->total = total;
    n->net_speed = (double)net_speed;
    n->outbox = calloc((size_t)rank_count, sizeof *n->outbox);
    n->outbox_count = calloc((size_t)rank_count, sizeof *n->outbox_count);
    if (!n->outbox || !n->outbox_count) ex_die(prog, "rank %d: out of memory for the outboxes", my_rank);
    for (k = 0; k < rank_count; k++)
        if (!(n->outbox[k] = malloc(RAYS_PER_MESSAGE * sizeof(brt_ray_state))))
            ex_die(prog, "rank %d: out of memory for the outboxes", my_rank);
}

/* After the trace: every send completed, buffers freed. */
static void network_free(network *n)
{
    int k;
    while (n->pending_count > 0) sends_progress(n);
    for (k = 0; k < rank_count; k++) free(n->outbox[k]);
    free(n->outbox);
    free(n->outbox_count);
    free(n->pending);
    free(n->inbox);
}

/* ---- this rank's rays and results ---------------------------------------------- */

typedef struct result {
    uint64_t index;
    brt_hit hit;
    uint32_t pad;
} result;

typedef struct share {
    const brt_ray *rays;
    size_t next, end;           /* this rank's range of the ray file */
    int occlusion;
    network *net;
    result *results;            /* rays finished here */
    size_t result_count, result_capacity;
} share;

static size_t share_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    share *s = user;
    size_t k;
    for (k = 0; k < max && s->next < s->end; k++, s->next++) {
        rays[k] = s->rays[s->next];
        tags[k] = s->next | (s->occlusion ? BRT_TAG_OCCLUSION : 0);
    }
    return k;
}

static void share_finished(void *user, const brt_ray *ray, const brt_hit *hit, const float normal[3],
                           uint32_t visits, uint64_t tag)
{
    share *s = user;
    result *r;
    (void)ray;
    (void)normal;
    (void)visits;
    s->results = must_grow(s->results, &s->result_capacity, s->result_count + 1, sizeof *s->results);
    r = &s->results[s->result_count++];
    memset(r, 0, sizeof *r);
    r->index = tag & ~BRT_TAG_OCCLUSION;
    r->hit = *hit;
    s->net->finished++;
}

/* Rank 0 places results in ray order. */
static void place(const result *results, size_t count, brt_hit *hits)
{
    size_t i;
    for (i = 0; i < count; i++) hits[results[i].index] = results[i].hit;
}

/* Every rank's results to rank 0, in chunks, rank after rank. */
static void gather_results(const share *s, brt_hit *hits)
{
    int k;
    if (my_rank != 0) {
        uint64_t count = s->result_count, first;
        MPI_Send(&count, 8, MPI_BYTE, 0, TAG_RESULTS, MPI_COMM_WORLD);
        for (first = 0; first < count; first += RESULTS_PER_MESSAGE) {
            uint64_t n = count - first < RESULTS_PER_MESSAGE ? count - first : RESULTS_PER_MESSAGE;
            MPI_Send(s->results + first, (int)(n * sizeof(result)), MPI_BYTE, 0, TAG_RESULTS,
                     MPI_COMM_WORLD);
        }
        return;
    }
    place(s->results, s->result_count, hits);
    for (k = 1; k < rank_count; k++) {
        uint64_t count, first;
        result *chunk = malloc(RESULTS_PER_MESSAGE * sizeof *chunk);
        if (!chunk) ex_die(prog, "out of memory gathering the hits");
        MPI_Recv(&count, 8, MPI_BYTE, k, TAG_RESULTS, MPI_COMM_WORLD, MPI_STATUS_IGNORE);
        for (first = 0; first < count; first += RESULTS_PER_MESSAGE) {
            uint64_t n = count - first < RESULTS_PER_MESSAGE ? count - first : RESULTS_PER_MESSAGE;
            MPI_Recv(chunk, (int)(n * sizeof *chunk), MPI_BYTE, k, TAG_RESULTS, MPI_COMM_WORLD,
                     MPI_STATUS_IGNORE);
            place(chunk, (size_t)n, hits);
        }
        free(chunk);
    }
}

/* ---- statistics ----------------------------------------------------------------- */

/* What each rank reports (one JSON object per rank and their sums), each
** name beside its value; the names in that order are kept for the JSON. */
#define STAT_COUNT 15
static const char *stat_names[STAT_COUNT];

static void stats_of(const brt_stats *st, const network *n, uint64_t *values)
{
    const struct { const char *name; uint64_t value; } figures[STAT_COUNT] = {
        {"rays_started", st->rays},
        {"rays_finished", n->finished},
        {"rays_sent", n->rays_sent},
        {"rays_received", n->rays_received},
        {"messages_sent", n->messages_sent},
        {"bytes_sent", n->bytes_sent},
        {"batch_loads", st->batch_loads},
        {"prototype_loads", st->prototype_loads},
        {"disk_bytes_read", st->disk_bytes_read},
        {"proxy_tests", st->proxy_tests},
        {"proxy_culled", st->proxy_culled},
        {"queued_visits", st->queued_visits},
        {"resident_visits", st->resident_visits},
        {"peak_rss_bytes", brt_peak_rss_bytes()},
        {"trace_microseconds", (uint64_t)(st->seconds * 1e6)}};
    size_t i;
    for (i = 0; i < STAT_COUNT; i++) {
        stat_names[i] = figures[i].name;
        values[i] = figures[i].value;
    }
}

/* The value of the figure called name in a set of values. */
static uint64_t stat_named(const uint64_t *values, const char *name)
{
    size_t i;
    for (i = 0; i < STAT_COUNT; i++)
        if (strcmp(stat_names[i], name) == 0) return values[i];
    return 0;
}

/* JSON of one set of values, into out (with room). */
static size_t stats_object(const uint64_t *v, char *out, size_t room, const char *indent)
{
    size_t used = 0, i;
    for (i = 0; i < STAT_COUNT && used < room; i++)
        used += (size_t)snprintf(out + used, room - used, "%s\"%s\": %llu%s", indent, stat_names[i],
                                 (unsigned long long)v[i], i + 1 < STAT_COUNT ? ",\n" : "\n");
    return used;
}

/* Rank 0 writes: the run, the sums over ranks, then each rank. */
static void stats_write(const options *o, const uint64_t *all, double seconds)
{
    uint64_t sum[STAT_COUNT] = {0};
    size_t room = (size_t)(rank_count + 2) * STAT_COUNT * 64 + 512, used;
    char *json = malloc(room);
    brt_error err;
    int k;
    size_t i;
    if (!json) ex_die(prog, "out of memory for the statistics");
    for (k = 0; k < rank_count; k++)
        for (i = 0; i < STAT_COUNT; i++) sum[i] += all[(size_t)k * STAT_COUNT + i];
    used = (size_t)snprintf(json, room,
                            "{\n  \"ranks\": %d,\n  \"proxies\": %d,\n  \"assign\": \"%s\",\n"
                            "  \"seconds\": %.6f,\n  \"total\": {\n",
                            rank_count, !o->t.no_proxy, o->round_robin ? "round-robin" : "runs", seconds);
    used += stats_object(sum, json + used, room - used, "    ");
    used += (size_t)snprintf(json + used, room - used, "  },\n  \"per_rank\": [\n");
    for (k = 0; k < rank_count; k++) {
        used += (size_t)snprintf(json + used, room - used, "    {\n");
        used += stats_object(all + (size_t)k * STAT_COUNT, json + used, room - used, "      ");
        used += (size_t)snprintf(json + used, room - used, "    }%s\n", k + 1 < rank_count ? "," : "");
    }
    used += (size_t)snprintf(json + used, room - used, "  ]\n}\n");
    if (brt_write_file_atomic(o->t.stats, json, used, &err) != BRT_OK) {
        unlink(o->t.hits);   /* a failed run leaves no output */
        ex_die(prog, "%s", err.message);
    }
    free(json);
    if (o->t.verbose || isatty(2))
        fprintf(stderr, "mpi_trace: %d ranks, %llu rays, %llu sent in %llu messages (%llu bytes), "
                "%llu loads, %.3f s\n", rank_count, (unsigned long long)stat_named(sum, "rays_started"),
                (unsigned long long)stat_named(sum, "rays_sent"),
                (unsigned long long)stat_named(sum, "messages_sent"),
                (unsigned long long)stat_named(sum, "bytes_sent"),
                (unsigned long long)stat_named(sum, "batch_loads"), seconds);
}

/* ---- the run ------------------------------------------------------------------- */

/* The scene file: SCENE itself when it is one (.brs), else the one rank 0
** builds or reuses for the mesh or pbrt file, as trace --batched does. */
static const char *prepare_scene(const options *o, char *path, size_t size)
{
    size_t len = strlen(o->t.input);
    const char *scene;
    ex_tracer_options t = o->t;
    ex_input in;
    unsigned long long point_tris;
    if (len > 4 && strcmp(o->t.input + len - 4, ".brs") == 0) return o->t.input;
    /* The default point size from rank 0's count of the input (every rank
    ** names the same scene file by it). */
    if (my_rank == 0) {
        ex_input_open(prog, o->t.input, &in);
        ex_tracer_point_size(&in, &t);
    }
    point_tris = t.point_tris;
    MPI_Bcast(&point_tris, 1, MPI_UNSIGNED_LONG_LONG, 0, MPI_COMM_WORLD);
    t.point_tris = point_tris;
    scene = ex_tracer_scene_path(prog, &t, path, size);
    if (my_rank == 0) {
        brt_scene_options scene_opt;
        int rebuilt;
        memset(&scene_opt, 0, sizeof scene_opt);
        scene_opt.point_tris = (uint32_t)t.point_tris;
        scene_opt.proxy_res = (uint32_t)t.res;
        scene_opt.interrupt = ex_catch_interrupts();
        brt_scene_close(ex_input_scene(prog, &in, scene, &scene_opt, &rebuilt));
        ex_input_close(&in);
    }
    MPI_Barrier(MPI_COMM_WORLD);
    return scene;
}

/* The scene, the rays and the owners, each rank's, agreed on. */
static brt_scene *open_everything(const options *o, brt_ray **rays, size_t *count, uint32_t **owner)
{
    char path_buffer[4096];
    const char *path = prepare_scene(o, path_buffer, sizeof path_buffer);
    brt_scene *scene = NULL;
    brt_error err;
    const char *failure = NULL;
    if (injected("open")) failure = "injected failure: the scene file does not open";
    else if (brt_scene_open(path, &scene, &err) != BRT_OK) failure = err.message;
    agree(failure);
    if (brt_rays_read(o->t.rays, rays, count, &err) != BRT_OK) failure = err.message;
    agree(failure);
    *owner = malloc(((size_t)brt_scene_point_count(scene) + 1) * sizeof **owner);
    if (!*owner) failure = "out of memory for the owners";
    else if (brt_scene_assign(scene, (uint32_t)rank_count, o->round_robin, *owner, &err) != BRT_OK)
        failure = err.message;
    agree(failure);
    return scene;
}

static void write_output(const options *o, const brt_scene *scene, const brt_hit *hits, size_t count)
{
    brt_error err;
    brt_result r;
    if (o->t.occlusion) {
        uint8_t *bytes = malloc(count ? count : 1);
        size_t i;
        if (!bytes) ex_die(prog, "out of memory for %lu occlusion bytes", (unsigned long)count);
        for (i = 0; i < count; i++) bytes[i] = hits[i].prim != BRT_NO_PRIM;
        r = brt_write_file_atomic(o->t.hits, bytes, count, &err);
        free(bytes);
    } else if (brt_scene_prototype_count(scene) > 0) {
        r = brt_hits_write_instanced(o->t.hits, hits, count, &err);
    } else {
        r = brt_hits_write(o->t.hits, hits, count, &err);
    }
    ex_check(prog, r, &err);
}

int main(int argc, char **argv)
{
    options o;
    brt_scene *scene;
    brt_ray *rays;
    brt_hit *hits = NULL;
    size_t count;
    uint32_t *owner, k;
    uint8_t *foreign;
    network net;
    share sh;
    brt_exchange exchange;
    brt_trace_options opt;
    brt_ray_source source;
    brt_stats stats;
    brt_error err;
    brt_result r;
    uint64_t mine[STAT_COUNT], *all = NULL;
    double start;

    MPI_Init(&argc, &argv);
    MPI_Comm_rank(MPI_COMM_WORLD, &my_rank);
    MPI_Comm_size(MPI_COMM_WORLD, &rank_count);
    atexit(abort_others);
    if (ex_wants_help(argc, argv)) {
        if (my_rank == 0) usage();
        MPI_Finalize();
        return 0;
    }
    parse_options_once(argc, argv, &o, my_rank);
    ex_catch_interrupts();
    scene = open_everything(&o, &rays, &count, &owner);

    foreign = malloc((size_t)brt_scene_point_count(scene) + 1);
    if (!foreign) ex_die(prog, "rank %d: out of memory", my_rank);
    for (k = 0; k < brt_scene_point_count(scene); k++) foreign[k] = owner[k] != (uint32_t)my_rank;
    network_init(&net, owner, count, o.net_speed);
    memset(&sh, 0, sizeof sh);
    sh.rays = rays;
    sh.next = count * (size_t)my_rank / (size_t)rank_count;
    sh.end = count * ((size_t)my_rank + 1) / (size_t)rank_count;
    sh.occlusion = o.t.occlusion;
    sh.net = &net;
    exchange.foreign = foreign;
    exchange.send = net_send;
    exchange.receive = net_receive;
    exchange.user = &net;
    memset(&opt, 0, sizeof opt);
    ex_tracer_trace_options(&o.t, &opt);
    opt.exchange = &exchange;
    opt.interrupt = ex_catch_interrupts();
    if (o.disk_speed) {
        opt.read_fn = ex_slow_disk_read;
        opt.read_user = &o.disk_speed;
    }
    source.next_rays = share_next;
    source.finished = share_finished;
    source.user = &sh;

    MPI_Barrier(MPI_COMM_WORLD);
    start = brt_seconds();
    r = brt_scene_trace_stream(scene, &opt, &source, &stats, &err);
    if (r != BRT_OK) trace_failed(r, err.message);
    network_free(&net);
    MPI_Barrier(MPI_COMM_WORLD);

    if (my_rank == 0 && !(hits = malloc((count ? count : 1) * sizeof *hits)))
        ex_die(prog, "out of memory for %lu hits", (unsigned long)count);
    gather_results(&sh, hits);
    stats_of(&stats, &net, mine);
    if (my_rank == 0 && !(all = malloc((size_t)rank_count * sizeof mine)))
        ex_die(prog, "out of memory for the statistics");
    MPI_Gather(mine, (int)sizeof mine, MPI_BYTE, all, (int)sizeof mine, MPI_BYTE, 0, MPI_COMM_WORLD);
    if (my_rank == 0) {
        if (ex_interrupted()) ex_die_interrupted(prog);
        write_output(&o, scene, hits, count);
        if (o.t.stats) stats_write(&o, all, brt_seconds() - start);
    }
    brt_scene_close(scene);
    free(hits);
    free(all);
    free(rays);
    free(owner);
    free(foreign);
    free(sh.results);
    MPI_Finalize();
    return 0;
}
