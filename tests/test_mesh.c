/*
** tests/test_mesh.c -- mesh loading (OBJ, PLY), ray and hit files, sizes
** and statistics JSON: the file contracts of README.md.
**
** Oracles are independent of the loaders: expected index lists written out
** by hand, a mesh encoded by this file's own PLY writer in every flavour,
** strtof for every parsed number, and little-endian bytes assembled with
** shifts for the record files.  Every malformed-input test checks the
** result code and the message (file name, line or element, reason), and
** runs both the memory parser and the streaming file loader.
*/
#include "test.h"
#include "util.h"
#include "../examples/lib/common.h"
#include "batchrt.h"

#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* ===================================================================== */
/* Helpers                                                               */
/* ===================================================================== */

/* A path in the scratch directory (a few may be alive at once). */
static const char *scratch_path(const char *name)
{
    static char paths[8][512];
    static int next;
    char *path = paths[next++ % 8];
    snprintf(path, 512, "%s/%s", test_tmpdir(), name);
    return path;
}

static const char *write_scratch(const char *name, const void *data, size_t size)
{
    const char *path = scratch_path(name);
    FILE *f = fopen(path, "wb");
    if (!f) return NULL;
    if (size && fwrite(data, 1, size, f) != size) path = NULL;
    if (fclose(f) != 0) path = NULL;
    return path;
}

/* A growable byte buffer for building test inputs. */
typedef struct buffer {
    unsigned char *data;
    size_t size, cap;
} buffer;

static void put_bytes(buffer *b, const void *data, size_t n)
{
    if (b->size + n > b->cap) {
        b->cap = 2 * (b->size + n) + 1024;
        b->data = realloc(b->data, b->cap);
        if (!b->data) abort();
    }
    memcpy(b->data + b->size, data, n);
    b->size += n;
}

static void put_text(buffer *b, const char *fmt, ...)
{
    char text[512];
    va_list ap;
    int n;
    va_start(ap, fmt);
    n = vsnprintf(text, sizeof text, fmt, ap);
    va_end(ap);
    put_bytes(b, text, (size_t)n);
}

/* Both entry points on one input: the memory parser (format given) and
** brt_mesh_load on a scratch file (format by content).  They must agree. */
typedef struct two_results {
    brt_result memory, file;
    brt_error memory_err, file_err;
    brt_mesh mesh; /* from the memory parser */
    char file_path[512];
} two_results;

static void parse_both(int is_ply, const char *text, size_t size, two_results *r)
{
    brt_mesh from_file;
    const char *name = is_ply ? "input.ply" : "input.obj";
    const char *path;
    memset(r, 0, sizeof *r);
    r->memory = is_ply ? brt_mesh_parse_ply(name, text, size, &r->mesh, &r->memory_err)
                       : brt_mesh_parse_obj(name, text, size, &r->mesh, &r->memory_err);
    path = write_scratch(name, text, size);
    snprintf(r->file_path, sizeof r->file_path, "%s", path ? path : "?");
    r->file = path ? brt_mesh_load(path, &from_file, &r->file_err) : BRT_EIO;
    if (r->file == BRT_OK) {
        EXPECT(r->memory == BRT_OK && from_file.vertex_count == r->mesh.vertex_count &&
                   from_file.triangle_count == r->mesh.triangle_count &&
                   memcmp(from_file.positions, r->mesh.positions,
                          12 * (size_t)r->mesh.vertex_count) == 0 &&
                   memcmp(from_file.indices, r->mesh.indices,
                          12 * (size_t)r->mesh.triangle_count) == 0,
               "file load and memory parse disagree");
        brt_mesh_free(&from_file);
    }
}

/* Malformed input: both paths fail with code, and each message is
** "NAME<where>: ...reason..." with NAME the memory name or the file path. */
static void expect_failure(int is_ply, const char *text, size_t size, brt_result code,
                           const char *where, const char *reason)
{
    two_results r;
    char prefix[600];
    parse_both(is_ply, text, size, &r);
    EXPECT(r.memory == code, "memory parse gave %d, want %d (%s)", r.memory, code,
           r.memory_err.message);
    EXPECT(r.file == code, "file load gave %d, want %d (%s)", r.file, code, r.file_err.message);
    snprintf(prefix, sizeof prefix, "%s%s", is_ply ? "input.ply" : "input.obj", where);
    EXPECT(strncmp(r.memory_err.message, prefix, strlen(prefix)) == 0 &&
               strstr(r.memory_err.message, reason),
           "message '%s' lacks '%s' or '%s'", r.memory_err.message, prefix, reason);
    snprintf(prefix, sizeof prefix, "%s%s", r.file_path, where);
    EXPECT(strncmp(r.file_err.message, prefix, strlen(prefix)) == 0 &&
               strstr(r.file_err.message, reason),
           "message '%s' lacks '%s' or '%s'", r.file_err.message, prefix, reason);
    EXPECT(strchr(r.memory_err.message, '\n') == NULL, "message is not one line");
    if (r.memory == BRT_OK) brt_mesh_free(&r.mesh);
}

static void expect_obj_failure(const char *text, const char *where, const char *reason)
{
    expect_failure(0, text, strlen(text), BRT_EPARSE, where, reason);
}

static void expect_ply_failure(const char *text, const char *where, const char *reason)
{
    expect_failure(1, text, strlen(text), BRT_EPARSE, where, reason);
}

/* Loads valid text and compares with the expected arrays exactly. */
static void expect_mesh(int is_ply, const char *text, const float *positions, uint32_t vertex_count,
                        const uint32_t *indices, uint32_t triangle_count)
{
    two_results r;
    uint32_t i;
    parse_both(is_ply, text, strlen(text), &r);
    CHECK(r.memory == BRT_OK && r.file == BRT_OK, "load failed: %s / %s", r.memory_err.message,
          r.file_err.message);
    EXPECT(r.mesh.vertex_count == vertex_count, "vertex count %u, want %u", r.mesh.vertex_count,
           vertex_count);
    EXPECT(r.mesh.triangle_count == triangle_count, "triangle count %u, want %u",
           r.mesh.triangle_count, triangle_count);
    for (i = 0; i < 3 * vertex_count && i < 3 * r.mesh.vertex_count; i++)
        EXPECT(r.mesh.positions[i] == positions[i], "coordinate %u is %g, want %g", i,
               r.mesh.positions[i], positions[i]);
    for (i = 0; i < 3 * triangle_count && i < 3 * r.mesh.triangle_count; i++)
        EXPECT(r.mesh.indices[i] == indices[i], "index %u is %u, want %u", i, r.mesh.indices[i],
               indices[i]);
    brt_mesh_free(&r.mesh);
}

/* ===================================================================== */
/* OBJ: valid inputs                                                     */
/* ===================================================================== */

static const float square[] = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0, 0.5f, 0.5f, 2};

static void test_obj_face_syntaxes(void)
{
    static const uint32_t expected[] = {0, 1, 2, 0, 2, 3, 1, 2, 3, 4, 0, 1, 2, 3, 4};
    expect_mesh(0,
                "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 0.5 2\n"
                "f 1 2 3\n"
                "f 1/1 3/2 4/3\n"
                "f 2//1 3//1 4//1\n"
                "f 5/1/1 1/2/1 2/3/1\n"
                "f 3/7/ 4/8/ 5//\n",
                square, 5, expected, 5);
}

static void test_obj_negative_indices(void)
{
    /* -1 is the last vertex defined so far, not the last of the file. */
    static const uint32_t expected[] = {0, 1, 2, 1, 2, 3, 4, 0, 3};
    expect_mesh(0,
                "v 0 0 0\nv 1 0 0\nv 1 1 0\nf -3 -2 -1\nv 0 1 0\nf -3/-3 -2//-1 -1/1/-2\n"
                "v 0.5 0.5 2\nf -1 1 -2\n",
                square, 5, expected, 3);
}

static void test_obj_fans(void)
{
    static const uint32_t expected[] = {4, 0, 1, 4, 1, 2, 4, 2, 3, 0, 1, 2, 0, 2, 3};
    expect_mesh(0, "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 0.5 2\nf 5 1 2 3 4\nf 1 2 3 4\n",
                square, 5, expected, 5);
}

static void test_obj_ignored_statements_and_crlf(void)
{
    static const uint32_t expected[] = {0, 1, 2, 2, 3, 4};
    expect_mesh(0,
                "# a comment\r\n\r\nmtllib scene.mtl\r\no object\r\ng group\r\ns off\r\n"
                "v 0 0 0 1\r\nv\t1 0 0\r\n  v 1 1 0 0.5 0.25 0.125\r\nvn 0 0 1\r\nvt 0.5 0.5\r\n"
                "usemtl gold\r\nf 1/1/1 2/1/1 3/1/1 # trailing comment\r\nl 1 2\r\np 3\r\n"
                "v 0 1 0\r\nv 0.5 0.5 2\r\n#f 9 9 9\r\nf 3 4 5", /* no final newline */
                square, 5, expected, 2);
}

static void test_obj_degenerate_kept(void)
{
    static const uint32_t expected[] = {0, 0, 0, 0, 1, 2, 1, 1, 2};
    expect_mesh(0, "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 1 1\nf 1 2 3\nf 2 2 3\n", square, 3, expected,
                3);
}

/* Every number is read as strtof reads the same text: random decimals of
** 1 to 17 significant digits with exponents, signs and leading zeros; the
** boundaries of the fast paths (2^24, 2^53, 10^+-10, 10^+-22); and decimals
** of 15-17 digits next to the midpoints between two floats, where rounding
** through double would round twice. */
enum { RANDOM_NUMBERS = 20000, MIDPOINTS = 3000 };

static void random_decimal(char *s, uint64_t *seed)
{
    int digits = 1 + (int)(brt_random_u64(seed) % 17);
    int point = (int)(brt_random_u64(seed) % (uint64_t)(digits + 1));
    int exponent = (int)(brt_random_u64(seed) % 46) - 25;   /* stays below FLT_MAX */
    int k = 0, d;
    if (brt_random_u64(seed) & 1) s[k++] = '-';
    for (d = 0; d < digits; d++) {
        if (d == point) s[k++] = '.';
        s[k++] = (char)('0' + brt_random_u64(seed) % 10);
    }
    if (brt_random_u64(seed) % 3 == 0) k += snprintf(s + k, 12, "e%d", exponent);
    s[k] = 0;
}

/* A decimal near the midpoint above a random float. */
static void near_midpoint(char *s, uint64_t *seed)
{
    float f = brt_random_float(seed) * 1e6f + 1e-3f;
    double midpoint = ((double)f + (double)nextafterf(f, INFINITY)) / 2;
    int digits = 15 + (int)(brt_random_u64(seed) % 3), step = (int)(brt_random_u64(seed) % 3) - 1;
    snprintf(s, 48, "%.*g", digits, step ? nextafter(midpoint, step * INFINITY) : midpoint);
}

static void test_obj_numbers_match_strtof(void)
{
    static const char *const fixed[] = {
        "16777216", "16777217", "16777215", "0.16777217", "1e10", "1e11", "1e-10", "1e-11",
        "-0", "+0.0", ".5", "5.", "-.25e+1", "0000123.4500", "3.4028235e38", "1.17549435e-38",
        "1e-45", "1.4e-45", "7e-46", "0.1", "0.3", "2.5e-7", "123456789012345678901234567890",
        "0.000000000000000000000000000000000001", "9999999.5", "4.9999999e-5", "8388608.5",
        "9007199254740993", "9007199254740992e-22", "1e22", "1e23", "1.000000059604645",
        "1.0000000596046448", "1.00000005960464477539", "0.500000029802322", "16777217.00000001",
        "-38857.312", "103965.125", "1e-30", "1e30", "1.0000000000000001e-30",
        /* within half a double ulp of a float midpoint: (float)strtod is wrong */
        "3861991874873638e-17", "494105893890295e9", "1871018295288086e-13",
        "3970599919966844e-22", "3136637568473816e-15", "5212865888067256e2"};
    const size_t n_fixed = sizeof fixed / sizeof fixed[0];
    const size_t n = n_fixed + RANDOM_NUMBERS + MIDPOINTS;
    uint64_t seed = test_seed();
    buffer text = {0, 0, 0};
    char(*numbers)[48] = malloc(n * sizeof *numbers);
    brt_mesh mesh;
    brt_error err;
    size_t i;
    CHECK(numbers, "out of memory");
    for (i = 0; i < n; i++) {
        if (i < n_fixed) snprintf(numbers[i], 48, "%s", fixed[i]);
        else if (i < n_fixed + RANDOM_NUMBERS) random_decimal(numbers[i], &seed);
        else near_midpoint(numbers[i], &seed);
        put_text(&text, "v %s 0 0\n", numbers[i]);
    }
    put_text(&text, "f 1 2 3\n");
    CHECK(brt_mesh_parse_obj("numbers.obj", text.data, text.size, &mesh, &err) == BRT_OK, "%s",
          err.message);
    for (i = 0; i < n && !test_failed(); i++) {
        float want = strtof(numbers[i], NULL), got = mesh.positions[3 * i];
        EXPECT(memcmp(&want, &got, sizeof want) == 0, "'%s' parsed as %.9g, strtof gives %.9g",
               numbers[i], got, want);
    }
    brt_mesh_free(&mesh);
    free(text.data);
    free(numbers);
}

/* A file of several MiB with a comment line longer than the 1 MiB read
** chunk: the streaming loader carries partial lines across chunks and
** grows its buffer, and gives exactly what the memory parser gives. */
static void test_obj_streaming_across_chunks(void)
{
    buffer text = {0, 0, 0};
    uint64_t seed = test_seed();
    two_results r;
    int i;
    put_text(&text, "#");
    for (i = 0; i < (3 << 19); i++) put_text(&text, "%c", 'a' + i % 26);
    put_text(&text, "\n");
    for (i = 0; i < 120000; i++) {
        put_text(&text, "v %.9g %.9g %.9g\n", brt_random_float(&seed), brt_random_float(&seed),
                 -brt_random_float(&seed));
        if (i >= 2) put_text(&text, "f %d -2 %d\n", i + 1, i - 1);
    }
    parse_both(0, (const char *)text.data, text.size, &r);
    free(text.data);
    CHECK(r.memory == BRT_OK && r.file == BRT_OK, "%s / %s", r.memory_err.message,
          r.file_err.message);
    EXPECT(r.mesh.triangle_count == 119998 && r.mesh.vertex_count == 120000, "counts %u %u",
           r.mesh.vertex_count, r.mesh.triangle_count);
    EXPECT(r.mesh.indices[3 * 500] == 502 && r.mesh.indices[3 * 500 + 1] == 501 &&
               r.mesh.indices[3 * 500 + 2] == 500,
           "wrong indices in the middle");
    brt_mesh_free(&r.mesh);
}

/* ===================================================================== */
/* OBJ: malformed inputs, one class per test                             */
/* ===================================================================== */

static void test_obj_garbage(void)
{
    static const char binary[] = "v 0 0 0\n\x7f\x01\x02garbage\x00\xff\n";
    expect_obj_failure("v 0 0 0\nv 1 0 0\nhello world\n", ":3:", "unknown statement 'hello'");
    expect_failure(0, binary, sizeof binary - 1, BRT_EPARSE, ":2:", "unknown statement");
    expect_obj_failure("v 0 0 zero\n", ":1:", "bad number 'zero'");
    expect_obj_failure("v 0 0 1e\n", ":1:", "bad number '1e'");
    expect_obj_failure("v 0 0 1.2.3\n", ":1:", "bad number");
    expect_obj_failure("v 0 0 0 0 0 0 0 0\n", ":1:", "too many values");
    expect_obj_failure("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3x\n", ":4:", "bad face vertex '3x'");
    expect_obj_failure("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3/1/1/1\n", ":4:", "bad face vertex");
    expect_obj_failure("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 /3\n", ":4:", "bad face vertex");
}

static void test_obj_missing_coordinates(void)
{
    expect_obj_failure("v 1 2\nf 1 1 1\n", ":1:", "vertex needs 3 coordinates, has 2");
    expect_obj_failure("v 1 2 3\nv\n", ":2:", "vertex needs 3 coordinates, has 0");
}

static void test_obj_non_finite(void)
{
    expect_obj_failure("v nan 0 0\n", ":1:", "coordinate 'nan' is not finite");
    expect_obj_failure("v 0 -inf 0\n", ":1:", "coordinate '-inf' is not finite");
    expect_obj_failure("v 0 0 NaN\n", ":1:", "coordinate 'NaN' is not finite");
    expect_obj_failure("v 0 0 0\nv 0 0 1e39\n", ":2:", "coordinate '1e39' is not finite");
}

static void test_obj_index_out_of_range(void)
{
    const char *v3 = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
    char text[256];
    snprintf(text, sizeof text, "%sf 0 1 2\n", v3);
    expect_obj_failure(text, ":4:", "vertex index 0 out of range");
    snprintf(text, sizeof text, "%sf 1 2 4\n", v3);
    expect_obj_failure(text, ":4:", "vertex index 4 out of range");
    snprintf(text, sizeof text, "%sf -4 -2 -1\n", v3);
    expect_obj_failure(text, ":4:", "vertex index -4 out of range");
    snprintf(text, sizeof text, "%sf 1 2 99999999999999999999999\n", v3);
    expect_obj_failure(text, ":4:", "out of range");
    expect_obj_failure("f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n",
                       ":1:", "vertex index 1 out of range");
}

static void test_obj_short_face(void)
{
    expect_obj_failure("v 0 0 0\nv 1 0 0\nf 1 2\n", ":3:", "face with fewer than 3 vertices (2)");
    expect_obj_failure("v 0 0 0\nf\n", ":2:", "fewer than 3 vertices (0)");
}

static void test_obj_no_triangles(void)
{
    expect_obj_failure("v 0 0 0\nv 1 0 0\nv 0 1 0\n", ": ", "no triangles");
    expect_obj_failure("", ": ", "no triangles");
    expect_obj_failure("# only a comment\n\n", ": ", "no triangles");
}

/* An error's place is where the first mistake is, however far into the
** file: past the readers' 1 MiB read buffer and the 65,536-triangle
** chunks of the stream, with CRLF lines counted once, and with the same
** mistake again later (the message names the first, not the last).  The
** expected places are counted here, from the text written. */
static void test_error_place_far_and_twice(void)
{
    static const char *const endings[] = {"\n", "\r\n"};
    const unsigned long faces = 150000;         /* about 1.2 MB of faces */
    buffer b = {0, 0, 0};
    unsigned long i, e;
    char where[64];
    for (e = 0; e < 2 && !test_failed(); e++) {
        const char *nl = endings[e];
        b.size = 0;
        put_text(&b, "v 0 0 0%sv 1 0 0%sv 0 1 0%s", nl, nl, nl);
        for (i = 0; i < faces; i++) put_text(&b, "f 1 2 3%s", nl);
        put_text(&b, "f 1 2 7%s", nl);                          /* line faces + 4 */
        for (i = 0; i < 4; i++) put_text(&b, "f 3 2 1%s", nl);
        put_text(&b, "f 1 2 9%s", nl);                          /* the same mistake again */
        snprintf(where, sizeof where, ":%lu:", faces + 4);
        expect_failure(0, (const char *)b.data, b.size, BRT_EPARSE, where, "vertex index 7 out of range");
    }
    /* Binary PLY: faces are counted as records of their element. */
    b.size = 0;
    put_text(&b, "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
                 "property float y\nproperty float z\nelement face %lu\n"
                 "property list uchar int vertex_indices\nend_header\n", faces);
    for (i = 0; i < 9; i++) {
        float x = (i == 3 || i == 7) ? 1.0f : 0.0f;
        put_bytes(&b, &x, 4);
    }
    for (i = 0; i < faces; i++) {
        unsigned char n = 3;
        int32_t v[3] = {0, 1, 2};
        if (i == faces - 70 || i == faces - 3) v[2] = (int32_t)(i == faces - 70 ? 5 : 6);
        put_bytes(&b, &n, 1);
        put_bytes(&b, v, sizeof v);
    }
    snprintf(where, sizeof where, ": element face %lu:", faces - 70);
    expect_failure(1, (const char *)b.data, b.size, BRT_EPARSE, where, "vertex index 5 out of range");
    /* ASCII PLY: lines, the header's included. */
    b.size = 0;
    put_text(&b, "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                 "property float z\nelement face %lu\nproperty list uchar int vertex_indices\nend_header\n"
                 "0 0 0\n1 0 0\n0 1 0\n", faces);
    for (i = 0; i < faces; i++) put_text(&b, i == 70000 ? "3 0 1 8\n" : i == 70001 ? "3 0 1 9\n" : "3 0 1 2\n");
    expect_failure(1, (const char *)b.data, b.size, BRT_EPARSE, ":70013:", "vertex index 8 out of range");
    free(b.data);
}

/* A truncated file is a shorter file: every proper prefix of this OBJ
** (short of its final newline) fails with a located parse error. */
static void test_obj_every_prefix(void)
{
    const char *text = "v 0 0 0\nv 1.5 0 0\nv 0 1e1 0\nf 1//2 2/3 3\n";
    brt_mesh whole;
    brt_error whole_err;
    size_t n;
    CHECK(brt_mesh_parse_obj("cut.obj", text, strlen(text) - 1, &whole, &whole_err) == BRT_OK,
          "without the final newline: %s", whole_err.message);
    brt_mesh_free(&whole);
    for (n = 0; n + 1 < strlen(text) && !test_failed(); n++) {
        brt_mesh mesh;
        brt_error err;
        brt_result rc = brt_mesh_parse_obj("cut.obj", text, n, &mesh, &err);
        EXPECT(rc == BRT_EPARSE && strncmp(err.message, "cut.obj:", 8) == 0,
               "prefix %zu: result %d, message '%s'", n, rc, err.message);
        if (rc == BRT_OK) brt_mesh_free(&mesh);
    }
}

/* The format comes from the content ("ply" on the first line), never from
** the file name. */
static void test_format_by_content(void)
{
    static const char ply[] = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                              "property float y\nproperty float z\nelement face 1\n"
                              "property list uchar int vertex_indices\nend_header\n"
                              "0 0 0\n1 0 0\n1 1 0\n3 2 1 0\n";
    static const char obj[] = "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 3 2 1\n";
    const char *ply_as_obj = write_scratch("really-ply.obj", ply, sizeof ply - 1);
    const char *obj_as_ply = write_scratch("really-obj.ply", obj, sizeof obj - 1);
    brt_mesh a, b;
    brt_error err;
    CHECK(ply_as_obj && obj_as_ply, "cannot write scratch files");
    CHECK(brt_mesh_load(ply_as_obj, &a, &err) == BRT_OK, "%s", err.message);
    CHECK(brt_mesh_load(obj_as_ply, &b, &err) == BRT_OK, "%s", err.message);
    EXPECT(a.triangle_count == 1 && b.triangle_count == 1 && a.indices[0] == 2 &&
               b.indices[0] == 2 && memcmp(a.positions, b.positions, 9 * sizeof(float)) == 0,
           "the two files differ");
    brt_mesh_free(&a);
    brt_mesh_free(&b);
}

static void test_missing_file(void)
{
    brt_mesh mesh;
    brt_error err;
    const char *path = scratch_path("does-not-exist.obj");
    CHECK(brt_mesh_load(path, &mesh, &err) == BRT_EIO, "missing file did not give BRT_EIO");
    EXPECT(strstr(err.message, path) && strstr(err.message, strerror(ENOENT)), "message '%s'",
           err.message);
}

/* ===================================================================== */
/* PLY: a writer for every flavour, used as the oracle's encoder         */
/* ===================================================================== */

enum { ASCII, LITTLE, BIG };
typedef enum { T_CHAR, T_UCHAR, T_SHORT, T_USHORT, T_INT, T_UINT, T_FLOAT, T_DOUBLE } ptype;
static const char *const ptype_names[] = {"char", "uchar", "short", "ushort",
                                          "int",  "uint",  "float", "double"};
static const char *const ptype_aliases[] = {"int8",  "uint8",  "int16",   "uint16",
                                            "int32", "uint32", "float32", "float64"};
static const int ptype_bytes[] = {1, 1, 2, 2, 4, 4, 4, 8};

static void put_value(buffer *b, int format, ptype type, double value)
{
    unsigned char bytes[8];
    uint64_t bits;
    int i, n = ptype_bytes[type];
    if (format == ASCII) {
        if (type >= T_FLOAT)
            put_text(b, " %.9g", value);
        else
            put_text(b, " %lld", (long long)value);
        return;
    }
    if (type == T_DOUBLE)
        memcpy(&bits, &value, 8);
    else if (type == T_FLOAT) {
        float f = (float)value;
        uint32_t u;
        memcpy(&u, &f, 4);
        bits = u;
    } else
        bits = (uint64_t)(int64_t)value;
    for (i = 0; i < n; i++)
        bytes[format == LITTLE ? i : n - 1 - i] = (unsigned char)(bits >> (8 * i));
    put_bytes(b, bytes, (size_t)n);
}

typedef struct ply_style {
    int format;
    ptype coord, count, index;
    int aliases; /* int32 instead of int, ... */
    int extras;  /* extra properties and an extra element */
} ply_style;

/* A test mesh: vertices and polygons (3..6 corners), and its expected fan. */
typedef struct poly_mesh {
    float positions[3 * 64];
    uint32_t vertex_count;
    uint32_t corners[64][6];
    int corner_count[64];
    int polygon_count;
    uint32_t fan[3 * 64 * 4];
    uint32_t triangle_count;
} poly_mesh;

static void random_poly_mesh(poly_mesh *m, uint64_t *seed)
{
    int p, k;
    memset(m, 0, sizeof *m);
    m->vertex_count = 40;
    for (k = 0; k < 3 * 40; k++) m->positions[k] = (brt_random_float(seed) - 0.5f) * 1000.0f;
    m->positions[0] = 1e-30f; /* tiny magnitudes and -0 survive exactly */
    m->positions[1] = -0.0f;
    m->polygon_count = 30;
    for (p = 0; p < m->polygon_count; p++) {
        m->corner_count[p] = 3 + (int)(brt_random_u64(seed) % 4);
        for (k = 0; k < m->corner_count[p]; k++)
            m->corners[p][k] = (uint32_t)(brt_random_u64(seed) % m->vertex_count);
        for (k = 1; k + 1 < m->corner_count[p]; k++) {
            uint32_t *t = m->fan + 3 * m->triangle_count++;
            t[0] = m->corners[p][0];
            t[1] = m->corners[p][k];
            t[2] = m->corners[p][k + 1];
        }
    }
}

static void ply_encode(buffer *b, const poly_mesh *m, const ply_style *s)
{
    static const char *const formats[] = {"ascii", "binary_little_endian", "binary_big_endian"};
    const char *const *names = s->aliases ? ptype_aliases : ptype_names;
    uint32_t v;
    int p, k;
    put_text(b, "ply\nformat %s 1.0\ncomment made by test_mesh.c\n", formats[s->format]);
    if (s->extras)
        put_text(
            b,
            "obj_info extras\nelement material 2\nproperty list uchar int ids\nproperty %s shine\n",
            names[T_FLOAT]);
    put_text(b, "element vertex %u\n", m->vertex_count);
    if (s->extras)
        put_text(b, "property %s red\nproperty %s weight\n", names[T_UCHAR], names[T_DOUBLE]);
    put_text(b, "property %s x\nproperty %s y\n", names[s->coord], names[s->coord]);
    if (s->extras) put_text(b, "property %s flags\n", names[T_SHORT]);
    put_text(b, "property %s z\n", names[s->coord]);
    if (s->extras) put_text(b, "property %s nx\n", names[T_FLOAT]);
    put_text(b, "element face %d\n", m->polygon_count);
    if (s->extras) put_text(b, "property %s group\n", names[T_USHORT]);
    put_text(b, "property list %s %s %s\n", names[s->count], names[s->index],
             s->extras ? "vertex_index" : "vertex_indices");
    if (s->extras)
        put_text(
            b,
            "property list uchar float texcoord\nelement edge 1\nproperty int a\nproperty int b\n");
    put_text(b, "end_header\n");
    if (s->extras)
        for (k = 0; k < 2; k++) {
            put_value(b, s->format, T_UCHAR, 2);
            put_value(b, s->format, T_INT, -7);
            put_value(b, s->format, T_INT, 70000);
            put_value(b, s->format, T_FLOAT, 0.5);
            if (s->format == ASCII) put_text(b, "\n");
        }
    for (v = 0; v < m->vertex_count; v++) {
        const float *xyz = m->positions + 3 * v;
        if (s->extras) {
            put_value(b, s->format, T_UCHAR, 255);
            put_value(b, s->format, T_DOUBLE, -1.25);
        }
        put_value(b, s->format, s->coord, xyz[0]);
        put_value(b, s->format, s->coord, xyz[1]);
        if (s->extras) put_value(b, s->format, T_SHORT, -300);
        put_value(b, s->format, s->coord, xyz[2]);
        if (s->extras) put_value(b, s->format, T_FLOAT, 1e30);
        if (s->format == ASCII) put_text(b, "\n");
    }
    for (p = 0; p < m->polygon_count; p++) {
        if (s->extras) put_value(b, s->format, T_USHORT, 65535);
        put_value(b, s->format, s->count, m->corner_count[p]);
        for (k = 0; k < m->corner_count[p]; k++)
            put_value(b, s->format, s->index, m->corners[p][k]);
        if (s->extras) {
            put_value(b, s->format, T_UCHAR, 2);
            put_value(b, s->format, T_FLOAT, 0.25);
            put_value(b, s->format, T_FLOAT, 0.75);
        }
        if (s->format == ASCII) put_text(b, "\n");
    }
    if (s->extras) {
        put_value(b, s->format, T_INT, 1);
        put_value(b, s->format, T_INT, 2);
        if (s->format == ASCII) put_text(b, "\n");
    }
}

static void ply_encode_obj(buffer *b, const poly_mesh *m)
{
    uint32_t v;
    int p, k;
    for (v = 0; v < m->vertex_count; v++)
        put_text(b, "v %.9g %.9g %.9g\n", m->positions[3 * v], m->positions[3 * v + 1],
                 m->positions[3 * v + 2]);
    for (p = 0; p < m->polygon_count; p++) {
        put_text(b, "f");
        for (k = 0; k < m->corner_count[p]; k++) put_text(b, " %u", m->corners[p][k] + 1);
        put_text(b, "\n");
    }
}

/* Exact equality with the expected mesh; memcmp keeps -0.0 apart from 0. */
static int same_as(const brt_mesh *got, const poly_mesh *want)
{
    return got->vertex_count == want->vertex_count && got->triangle_count == want->triangle_count &&
        memcmp(got->positions, want->positions, 12 * (size_t)want->vertex_count) == 0 &&
        memcmp(got->indices, want->fan, 12 * (size_t)want->triangle_count) == 0;
}

/* ===================================================================== */
/* PLY: valid inputs                                                     */
/* ===================================================================== */

/* The same geometry in OBJ and in every PLY flavour, coordinate type,
** count and index type, with and without extra properties and elements,
** loads to identical positions and indices. */
static void test_ply_all_flavours_match_obj(void)
{
    static const ptype counts[] = {T_UCHAR, T_CHAR, T_INT, T_USHORT, T_UINT};
    static const ptype indices[] = {T_INT, T_UINT, T_UCHAR, T_SHORT, T_USHORT};
    uint64_t seed = test_seed();
    poly_mesh *m = malloc(sizeof *m);
    buffer text = {0, 0, 0};
    two_results r;
    ply_style s;
    int i;
    CHECK(m, "out of memory");
    random_poly_mesh(m, &seed);
    ply_encode_obj(&text, m);
    parse_both(0, (const char *)text.data, text.size, &r);
    EXPECT(r.memory == BRT_OK && r.file == BRT_OK && same_as(&r.mesh, m), "OBJ differs: %s",
           r.memory_err.message);
    if (r.memory == BRT_OK) brt_mesh_free(&r.mesh);
    for (i = 0; i < 3 * 2 * 2 * 5 && !test_failed(); i++) {
        s.format = i % 3;
        s.coord = (i / 3) % 2 ? T_DOUBLE : T_FLOAT;
        s.extras = (i / 6) % 2;
        s.aliases = (i / 12) % 2;
        s.count = counts[(i / 12) % 5];
        s.index = indices[i % 5];
        text.size = 0;
        ply_encode(&text, m, &s);
        parse_both(1, (const char *)text.data, text.size, &r);
        EXPECT(r.memory == BRT_OK && r.file == BRT_OK && same_as(&r.mesh, m),
               "format %d coord %s count %s index %s extras %d: %s %s", s.format,
               ptype_names[s.coord], ptype_names[s.count], ptype_names[s.index], s.extras,
               r.memory_err.message, r.file_err.message);
        if (r.memory == BRT_OK) brt_mesh_free(&r.mesh);
    }
    free(text.data);
    free(m);
}

static void test_ply_ascii_details(void)
{
    /* CRLF, comments, blank lines between records, a quad fanned. */
    static const uint32_t expected[] = {0, 1, 2, 0, 2, 3};
    expect_mesh(1,
                "ply\r\nformat ascii 1.0\r\ncomment hi\r\nelement vertex 4\r\nproperty float x\r\n"
                "property float y\r\nproperty float z\r\nelement face 1\r\n"
                "property list uchar int vertex_indices\r\nend_header\r\n"
                "0 0 0\r\n1 0 0\r\n\r\n1 1 0\r\n0 1 0\r\n4 0 1 2 3\r\n",
                square, 4, expected, 2);
}

/* A binary PLY of several MiB: records of 24 and 13 bytes straddle the
** 1 MiB read chunks; file and memory agree and every value is right. */
static void test_ply_streaming_across_chunks(void)
{
    enum { VERTICES = 150000 };
    buffer b = {0, 0, 0};
    two_results r;
    uint32_t i;
    put_text(&b, "ply\nformat binary_big_endian 1.0\nelement vertex %d\nproperty double x\n"
                 "property double y\nproperty double z\nelement face %d\n"
                 "property list uchar int vertex_indices\nend_header\n",
             VERTICES, VERTICES - 2);
    for (i = 0; i < VERTICES; i++) {
        put_value(&b, BIG, T_DOUBLE, i);
        put_value(&b, BIG, T_DOUBLE, -0.5 * i);
        put_value(&b, BIG, T_DOUBLE, 0.25);
    }
    for (i = 0; i + 2 < VERTICES; i++) {
        put_value(&b, BIG, T_UCHAR, 3);
        put_value(&b, BIG, T_INT, i);
        put_value(&b, BIG, T_INT, i + 2);
        put_value(&b, BIG, T_INT, i + 1);
    }
    parse_both(1, (const char *)b.data, b.size, &r);
    free(b.data);
    CHECK(r.memory == BRT_OK && r.file == BRT_OK, "%s / %s", r.memory_err.message,
          r.file_err.message);
    CHECK(r.mesh.vertex_count == VERTICES && r.mesh.triangle_count == VERTICES - 2, "counts");
    for (i = 0; i < VERTICES && !test_failed(); i++)
        EXPECT(r.mesh.positions[3 * i] == (float)i &&
                   r.mesh.positions[3 * i + 1] == -0.5f * (float)i &&
                   r.mesh.positions[3 * i + 2] == 0.25f,
               "vertex %u", i);
    for (i = 0; i + 2 < VERTICES && !test_failed(); i++)
        EXPECT(r.mesh.indices[3 * i] == i && r.mesh.indices[3 * i + 1] == i + 2 &&
                   r.mesh.indices[3 * i + 2] == i + 1,
               "triangle %u", i);
    brt_mesh_free(&r.mesh);
}

/* ===================================================================== */
/* PLY: malformed inputs                                                 */
/* ===================================================================== */

#define PLY_HEAD \
    "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float " \
    "z\n"
#define PLY_FACE "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
#define PLY_VERTS "0 0 0\n1 0 0\n0 1 0\n"

static void test_ply_bad_header(void)
{
    brt_mesh mesh;
    brt_error err;
    EXPECT(brt_mesh_parse_ply("x.ply", "plx\nformat ascii 1.0\n", 20, &mesh, &err) == BRT_EPARSE &&
               strcmp(err.message, "x.ply:1: not a PLY file") == 0,
           "'%s'", err.message);
    expect_ply_failure("ply\nformat binary_middle_endian 1.0\n" PLY_FACE,
                       ":2:", "bad PLY header: unknown format");
    expect_ply_failure("ply\nformat ascii 2.0\n", ":2:", "unknown format");
    expect_ply_failure(
        "ply\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n" PLY_FACE
            PLY_VERTS "3 0 1 2\n",
        ":8:", "no format line");
    expect_ply_failure(PLY_HEAD "element face 1\nproperty list uchar int vertex_indices\n",
                       ":8:", "no end_header");
    expect_ply_failure(PLY_HEAD "property float128 w\n" PLY_FACE, ":7:", "unknown type 'float128'");
    expect_ply_failure("ply\nformat ascii 1.0\nproperty float x\n",
                       ":3:", "property before any element");
    expect_ply_failure(PLY_HEAD "flavour sweet\n" PLY_FACE, ":7:", "unknown line");
    expect_ply_failure(PLY_HEAD
                       "element face 1\nproperty list float int vertex_indices\nend_header\n",
                       ":8:", "list count type must be an integer");
    expect_ply_failure(PLY_HEAD
                       "element face 1\nproperty list uchar float vertex_indices\nend_header\n",
                       ":8:", "vertex indices must have an integer type");
    expect_ply_failure(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty int y\n",
        ":5:", "vertex property y must be float or double");
    expect_ply_failure(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n" PLY_FACE,
        ":8:", "needs properties x, y and z");
    expect_ply_failure(PLY_HEAD "element face 1\nproperty list uchar int corners\nend_header\n",
                       ":9:", "needs one list vertex_indices");
    expect_ply_failure(PLY_HEAD "element face x\n", ":7:", "element needs a name and a count");
    expect_ply_failure(PLY_HEAD "element face -1\n", ":7:", "element needs a name and a count");
    expect_ply_failure("ply\nformat ascii 1.0\nelement vertex 99999999999\n",
                       ":3:", "too many vertices");
    expect_ply_failure(PLY_HEAD "element vertex 2\n", ":7:", "a second vertex element");
}

static void test_ply_ascii_bad_values(void)
{
    expect_ply_failure(PLY_HEAD PLY_FACE "0 0 0\n1 zero 0\n", ":11:", "bad value 'zero'");
    expect_ply_failure(PLY_HEAD PLY_FACE "0 0 0\n1 0\n", ":11:", "too few values");
    expect_ply_failure(PLY_HEAD PLY_FACE "0 0 0\n1 0 0 7\n", ":11:", "too many values");
    expect_ply_failure(PLY_HEAD PLY_FACE PLY_VERTS "3 0 1 2 3\n", ":13:", "too many values");
    expect_ply_failure(PLY_HEAD PLY_FACE PLY_VERTS "256 0 1 2\n", ":13:", "bad value '256'");
    expect_ply_failure(PLY_HEAD PLY_FACE PLY_VERTS "3 0 1.5 2\n", ":13:", "bad value '1.5'");
}

static void test_ply_non_finite(void)
{
    expect_ply_failure(PLY_HEAD PLY_FACE "0 0 0\n1 nan 0\n0 1 0\n3 0 1 2\n",
                       ":11:", "coordinate y is not finite");
    expect_ply_failure(PLY_HEAD PLY_FACE "0 0 0\n1 0 0\n0 1 1e40\n3 0 1 2\n",
                       ":12:", "coordinate z is not finite");
}

static void test_ply_index_out_of_range(void)
{
    expect_ply_failure(PLY_HEAD PLY_FACE PLY_VERTS "3 0 1 3\n",
                       ":13:", "vertex index 3 out of range (3 vertices)");
    expect_ply_failure(PLY_HEAD PLY_FACE PLY_VERTS "3 0 -1 2\n",
                       ":13:", "vertex index -1 out of range");
}

static void test_ply_short_face(void)
{
    expect_ply_failure(PLY_HEAD PLY_FACE PLY_VERTS "2 0 1\n",
                       ":13:", "face with fewer than 3 vertices (2)");
    expect_ply_failure(
        PLY_HEAD "element face 1\nproperty list char int vertex_indices\nend_header\n" PLY_VERTS
                 "-1\n",
        ":13:", "negative list count");
}

static void test_ply_truncated_and_empty(void)
{
    expect_ply_failure(PLY_HEAD PLY_FACE PLY_VERTS, ":12:", "file truncated in element face");
    expect_ply_failure(
        PLY_HEAD "element face 0\nproperty list uchar int vertex_indices\nend_header\n" PLY_VERTS,
        ": ", "no triangles");
}

/* Binary errors are located by element and record. */
static void test_ply_binary_errors(void)
{
    static const uint32_t expected_fan[] = {0, 1, 2};
    ply_style s = {LITTLE, T_FLOAT, T_UCHAR, T_INT, 0, 0};
    poly_mesh *m = calloc(1, sizeof *m);
    buffer b = {0, 0, 0};
    size_t full, cut;
    CHECK(m, "out of memory");
    m->vertex_count = 3;
    memcpy(m->positions, square, sizeof(float) * 9);
    m->polygon_count = 2;
    m->corner_count[0] = m->corner_count[1] = 3;
    memcpy(m->corners[0], expected_fan, sizeof expected_fan);
    memcpy(m->corners[1], expected_fan, sizeof expected_fan);
    ply_encode(&b, m, &s);
    full = b.size;
    /* every proper prefix of the body is truncated at some record */
    for (cut = full - 1; cut > full - 2 * 13 - 3 * 12 && !test_failed(); cut--) {
        char where[64];
        size_t body = cut - (full - 2 * 13 - 3 * 12);
        if (body >= 36)
            snprintf(where, sizeof where, ": element face %zu:", (body - 36) / 13);
        else
            snprintf(where, sizeof where, ": element vertex %zu:", body / 12);
        expect_failure(1, (const char *)b.data, cut, BRT_EPARSE, where, "file truncated");
    }
    b.data[full - 4] = 3; /* low byte of face 1's last index: 3, out of range */
    expect_failure(1, (const char *)b.data, full, BRT_EPARSE,
                   ": element face 1:", "vertex index 3 out of range");
    b.data[full - 4] = 2;
    b.data[full - 13] = 2; /* count of face 1: 2 */
    expect_failure(1, (const char *)b.data, full, BRT_EPARSE,
                   ": element face 1:", "fewer than 3 vertices (2)");
    b.data[full - 13] = 3;
    memset(b.data + full - 2 * 13 - 3 * 12 + 12 + 4, 0xff, 4); /* vertex 1, y = NaN */
    expect_failure(1, (const char *)b.data, full, BRT_EPARSE,
                   ": element vertex 1:", "coordinate y is not finite");
    /* a huge list count in a short file is "truncated", not a huge allocation */
    s.count = T_UINT;
    b.size = 0;
    ply_encode(&b, m, &s);
    memset(b.data + b.size - 16, 0xff, 4); /* face 1 claims 2^32 - 1 corners */
    expect_failure(1, (const char *)b.data, b.size, BRT_EPARSE,
                   ": element face 1:", "file truncated");
    /* doubles beyond the float range */
    s.count = T_UCHAR;
    s.coord = T_DOUBLE;
    s.format = BIG;
    b.size = 0;
    ply_encode(&b, m, &s);
    {
        double huge = 1e300;
        unsigned char bytes[8];
        uint64_t bits;
        int i;
        memcpy(&bits, &huge, 8);
        for (i = 0; i < 8; i++) bytes[i] = (unsigned char)(bits >> (56 - 8 * i));
        memcpy(b.data + b.size - 2 * 13 - 3 * 24 + 24 + 16, bytes, 8); /* vertex 1, z */
    }
    expect_failure(1, (const char *)b.data, b.size, BRT_EPARSE,
                   ": element vertex 1:", "coordinate z is not finite");
    free(b.data);
    free(m);
}

/* Random corruption of valid files in every flavour: a result code and a
** message naming the input, never a crash (run under make sanitize too). */
static void test_ply_obj_fuzz(void)
{
    uint64_t seed = test_seed();
    poly_mesh *m = malloc(sizeof *m);
    buffer b = {0, 0, 0};
    int round;
    CHECK(m, "out of memory");
    random_poly_mesh(m, &seed);
    for (round = 0; round < 2000 && !test_failed(); round++) {
        ply_style s = {round % 4,     (round / 4) % 2 ? T_DOUBLE : T_FLOAT, T_UCHAR, T_INT, 0,
                       round % 3 == 0};
        brt_mesh mesh;
        brt_error err;
        brt_result rc;
        int flips = 1 + (int)(brt_random_u64(&seed) % 4), k;
        b.size = 0;
        if (s.format == 3)
            ply_encode_obj(&b, m);
        else
            ply_encode(&b, m, &s);
        for (k = 0; k < flips; k++)
            b.data[brt_random_u64(&seed) % b.size] = (unsigned char)brt_random_u64(&seed);
        b.size -= (size_t)(brt_random_u64(&seed) % 3 == 0 ? brt_random_u64(&seed) % b.size : 0);
        rc = s.format == 3 ? brt_mesh_parse_obj("fuzz", b.data, b.size, &mesh, &err)
                           : brt_mesh_parse_ply("fuzz", b.data, b.size, &mesh, &err);
        if (rc == BRT_OK)
            brt_mesh_free(&mesh);
        else
            EXPECT(rc == BRT_EPARSE && strncmp(err.message, "fuzz:", 5) == 0 &&
                       !strchr(err.message, '\n'),
                   "round %d: result %d, message '%s'", round, rc, err.message);
    }
    free(b.data);
    free(m);
}

/* ===================================================================== */
/* Shared meshes and bounds                                              */
/* ===================================================================== */

static void expect_shared_counts(const char *name, uint32_t vertices, uint32_t triangles)
{
    const char *path = test_shared_mesh(name);
    brt_mesh mesh;
    brt_error err;
    if (!path) {
        test_skip("%s: ../shared/data/meshes not found", name);
        return;
    }
    CHECK(brt_mesh_load(path, &mesh, &err) == BRT_OK, "%s", err.message);
    EXPECT(mesh.vertex_count == vertices && mesh.triangle_count == triangles,
           "%s: %u vertices, %u triangles; README says %u, %u", name, mesh.vertex_count,
           mesh.triangle_count, vertices, triangles);
    brt_mesh_free(&mesh);
}

static void test_shared_bunny_tiny(void)
{
    const char *path = test_shared_mesh("bunny_tiny.obj");
    static const float lo[3] = {-4.958f, -0.003149f, -3.73f}, hi[3] = {4.949f, 9.655f, 3.811f};
    float bmin[3], bmax[3];
    brt_mesh mesh;
    brt_error err;
    int a;
    if (!path) {
        test_skip("../shared/data/meshes not found");
        return;
    }
    expect_shared_counts("bunny_tiny.obj", 1839, 3674);
    CHECK(brt_mesh_load(path, &mesh, &err) == BRT_OK, "%s", err.message);
    brt_mesh_bounds(&mesh, bmin, bmax);
    for (a = 0; a < 3; a++) /* the README prints 4 significant digits */
        EXPECT(fabsf(bmin[a] - lo[a]) <= 1e-3f * fabsf(lo[a]) &&
                   fabsf(bmax[a] - hi[a]) <= 1e-3f * fabsf(hi[a]),
               "axis %d: bounds [%g, %g], README [%g, %g]", a, bmin[a], bmax[a], lo[a], hi[a]);
    brt_mesh_free(&mesh);
}

static void test_shared_bunny(void)
{
    expect_shared_counts("bunny.obj.gz", 35947, 69451);
}

/* Bounds cover referenced vertices only; an empty mesh is +inf / -inf. */
static void test_mesh_bounds(void)
{
    const char *text = "v 1 2 3\nv 100 100 100\nv -1 5 0\nv 0 0 -4\nf 1 3 4\n";
    brt_mesh mesh, empty;
    brt_error err;
    float bmin[3], bmax[3];
    CHECK(brt_mesh_parse_obj("b.obj", text, strlen(text), &mesh, &err) == BRT_OK, "%s",
          err.message);
    brt_mesh_bounds(&mesh, bmin, bmax);
    EXPECT(bmin[0] == -1 && bmin[1] == 0 && bmin[2] == -4 && bmax[0] == 1 && bmax[1] == 5 &&
               bmax[2] == 3,
           "bounds (%g %g %g) (%g %g %g)", bmin[0], bmin[1], bmin[2], bmax[0], bmax[1], bmax[2]);
    brt_mesh_free(&mesh);
    EXPECT(mesh.positions == NULL && mesh.triangle_count == 0, "brt_mesh_free does not reset");
    memset(&empty, 0, sizeof empty);
    brt_mesh_bounds(&empty, bmin, bmax);
    EXPECT(bmin[0] == INFINITY && bmax[2] == -INFINITY, "empty bounds (%g, %g)", bmin[0], bmax[2]);
}

/* ===================================================================== */
/* Ray and hit files                                                     */
/* ===================================================================== */

/* Little-endian bytes of 32-bit words, assembled with shifts: the oracle. */
static void le_words(const uint32_t *words, size_t n, unsigned char *out)
{
    size_t i;
    for (i = 0; i < n; i++) {
        out[4 * i] = (unsigned char)words[i];
        out[4 * i + 1] = (unsigned char)(words[i] >> 8);
        out[4 * i + 2] = (unsigned char)(words[i] >> 16);
        out[4 * i + 3] = (unsigned char)(words[i] >> 24);
    }
}

/* Random bit patterns (NaN payloads included) go through unchanged. */
static void test_io_rays_round_trip(void)
{
    enum { N = 1000 };
    uint64_t seed = test_seed();
    uint32_t *words = malloc(N * 8 * sizeof *words);
    unsigned char *expected = malloc(N * 32);
    brt_ray *rays = malloc(N * sizeof *rays), *back = NULL;
    unsigned char *bytes;
    const char *path = scratch_path("round.rays");
    size_t count = 0, size = 0, i;
    brt_error err;
    CHECK(words && expected && rays, "out of memory");
    for (i = 0; i < N * 8; i++) words[i] = (uint32_t)brt_random_u64(&seed);
    for (i = 0; i < N; i++) memcpy(&rays[i], words + 8 * i, 32);
    le_words(words, N * 8, expected);
    CHECK(brt_rays_write(path, rays, N, &err) == BRT_OK, "%s", err.message);
    bytes = tu_slurp(path, &size);
    EXPECT(bytes && size == N * 32 && memcmp(bytes, expected, size) == 0, "ray file bytes differ");
    free(bytes);
    CHECK(brt_rays_read(path, &back, &count, &err) == BRT_OK, "%s", err.message);
    EXPECT(count == N && memcmp(back, rays, N * sizeof *rays) == 0, "rays read back differ");
    free(back);
    free(rays);
    free(expected);
    free(words);
}

static void test_io_hits_round_trip(void)
{
    enum { N = 1000 };
    uint64_t seed = test_seed();
    uint32_t *words = malloc(N * 4 * sizeof *words);
    unsigned char *expected = malloc(N * 16);
    brt_hit *hits = malloc(N * sizeof *hits), *back = NULL;
    unsigned char *bytes;
    const char *path = scratch_path("round.hits");
    size_t count = 0, size = 0, i;
    brt_error err;
    CHECK(words && expected && hits, "out of memory");
    for (i = 0; i < N * 4; i++) words[i] = (uint32_t)brt_random_u64(&seed);
    for (i = 0; i < N; i++) {
        memcpy(&hits[i], words + 4 * i, 16);
        hits[i].inst = BRT_NO_INST;   /* the short form: no instances */
    }
    brt_hit_clear(&hits[0]); /* the miss record: inf, 0xFFFFFFFF, 0, 0 */
    memcpy(words, &hits[0], 16);
    le_words(words, N * 4, expected);
    EXPECT(memcmp(expected, "\x00\x00\x80\x7f\xff\xff\xff\xff\0\0\0\0\0\0\0\0", 16) == 0,
           "miss record bytes");
    CHECK(brt_hits_write(path, hits, N, &err) == BRT_OK, "%s", err.message);
    bytes = tu_slurp(path, &size);
    EXPECT(bytes && size == N * 16 && memcmp(bytes, expected, size) == 0, "hit file bytes differ");
    free(bytes);
    CHECK(brt_hits_read(path, &back, &count, NULL, &err) == BRT_OK, "%s", err.message);
    EXPECT(count == N && memcmp(back, hits, N * sizeof *hits) == 0, "hits read back differ");
    free(back);
    free(hits);
    free(expected);
    free(words);
}

static void test_io_bad_sizes(void)
{
    static const unsigned char zeros[40];
    const char *rays = write_scratch("odd.rays", zeros, 33);
    const char *hits = write_scratch("odd.hits", zeros, 17);
    brt_ray *r = NULL;
    brt_hit *h = NULL;
    size_t count;
    brt_error err;
    CHECK(rays && hits, "cannot write scratch files");
    EXPECT(brt_rays_read(rays, &r, &count, &err) == BRT_EPARSE && strstr(err.message, rays) &&
               strstr(err.message, "size 33"),
           "33-byte ray file: '%s'", err.message);
    EXPECT(brt_hits_read(hits, &h, &count, NULL, &err) == BRT_EPARSE && strstr(err.message, hits) &&
               strstr(err.message, "size 17"),
           "17-byte hit file: '%s'", err.message);
    hits = write_scratch("32.hits", zeros, 32); /* a whole number of hits */
    CHECK(brt_hits_read(hits, &h, &count, NULL, &err) == BRT_OK && count == 2, "32-byte hit file");
    free(h);
}

static void test_io_empty_and_missing(void)
{
    const char *empty = write_scratch("empty.rays", "", 0);
    const char *missing = scratch_path("missing.rays");
    brt_ray *rays = NULL;
    size_t count = 99;
    brt_error err;
    CHECK(empty, "cannot write scratch file");
    CHECK(brt_rays_read(empty, &rays, &count, &err) == BRT_OK && count == 0, "empty ray file: %s",
          err.message);
    free(rays);
    EXPECT(brt_rays_read(missing, &rays, &count, &err) == BRT_EIO && strstr(err.message, missing) &&
               strstr(err.message, strerror(ENOENT)),
           "missing ray file: '%s'", err.message);
}

static void test_io_write_into_missing_directory(void)
{
    const char *path = scratch_path("no-such-dir/out.hits");
    brt_hit hit;
    brt_error err;
    struct stat st;
    brt_hit_clear(&hit);
    EXPECT(brt_hits_write(path, &hit, 1, &err) == BRT_EIO && strstr(err.message, path), "'%s'",
           err.message);
    EXPECT(stat(path, &st) != 0, "a file was left behind");
    EXPECT(brt_stats_write_json(path, &(brt_stats){0}, &err) == BRT_EIO,
           "stats into a missing directory");
}

/* ===================================================================== */
/* Sizes and statistics                                                  */
/* ===================================================================== */

static void test_io_parse_size(void)
{
    static const struct {
        const char *text;
        uint64_t bytes;
    } good[] = {
        {"512M", 512ull << 20}, {"64K", 64ull << 10}, {"2G", 2ull << 30}, {"100", 100}, {"1", 1}};
    static const char *const bad[] = {"",   "-1", "0",  "12X",         "99999999999999999999G",
                                      "0K", "M",  " 5", "17179869184G"};
    size_t i;
    for (i = 0; i < sizeof good / sizeof good[0]; i++) {
        uint64_t bytes = 0;
        EXPECT(brt_parse_size(good[i].text, &bytes) == BRT_OK && bytes == good[i].bytes,
               "'%s' gave %llu", good[i].text, (unsigned long long)bytes);
    }
    for (i = 0; i < sizeof bad / sizeof bad[0]; i++) {
        uint64_t bytes = 0;
        EXPECT(brt_parse_size(bad[i], &bytes) == BRT_EARG, "'%s' accepted", bad[i]);
    }
}

/* The one copy of each small utility against references written
** apart from it: byte layouts spelled out, SplitMix64's published first
** outputs for seed 0 (from the algorithm as Steele, Lea and Flood give it,
** computed in Python), the growth rule and the validity rule as stated. */
static void test_io_utilities(void)
{
    static const unsigned char le[12] = {0x78, 0x56, 0x34, 0x12, 0xEF, 0xCD, 0xAB, 0x89,
                                         0x67, 0x45, 0x23, 0x01};
    static const uint64_t splitmix0[3] = {0xE220A8397B1DCDAFull, 0x6E789E6AA1B965F4ull,
                                          0x06C45D188009454Full};
    unsigned char buf[12];
    uint64_t state = 0;
    size_t cap = 0, i;
    uint32_t *items = NULL, *grown;
    brt_ray ray = {{0, 0, 0}, {0, 0, 1}, 0, INFINITY};
    brt_put_le32(buf, 0x12345678u);
    brt_put_le64(buf + 4, 0x0123456789ABCDEFull);
    EXPECT(memcmp(buf, le, sizeof le) == 0, "brt_put_le32/64: not little-endian");
    EXPECT(brt_get_le32(le) == 0x12345678u && brt_get_le64(le + 4) == 0x0123456789ABCDEFull,
           "brt_get_le32/64: not little-endian");
    for (i = 0; i < 3; i++)
        EXPECT(brt_random_u64(&state) == splitmix0[i], "SplitMix64 output %lu differs",
               (unsigned long)i);
    EXPECT(brt_mix64(1) == 0x5692161D100B05E5ull && brt_mix64(0) == 0, "brt_mix64 differs");
    for (i = 0; i < 1000; i++) {
        size_t old = cap;
        grown = brt_grow(items, &cap, i + 1, sizeof *items);
        CHECK(grown != NULL, "brt_grow failed at %lu", (unsigned long)i);
        EXPECT(cap >= i + 1 && (cap == old || cap >= 2 * old), "brt_grow: capacity %lu after %lu",
               (unsigned long)cap, (unsigned long)old);
        EXPECT(i + 1 > old || grown == items, "brt_grow moved an array that had room");
        items = grown;
        items[i] = (uint32_t)i * 7u;
    }
    for (i = 0; i < 1000; i++) EXPECT(items[i] == (uint32_t)i * 7u, "brt_grow lost item %lu", (unsigned long)i);
    free(items);
    EXPECT(brt_ray_valid(&ray), "a valid ray refused");
    ray.tfar = -1;
    EXPECT(!brt_ray_valid(&ray), "tnear > tfar accepted");
    ray.tfar = NAN;
    EXPECT(!brt_ray_valid(&ray), "NaN tfar accepted");
    ray.tfar = 1;
    ray.dir[2] = 0;
    EXPECT(!brt_ray_valid(&ray), "zero direction accepted");
    ray.dir[2] = 1;
    ray.org[1] = INFINITY;
    EXPECT(!brt_ray_valid(&ray), "infinite origin accepted");
}

/* brt_atomic_open/close: the file appears under its name only when
** complete; a failure leaves neither it nor the temporary file. */
static void test_io_atomic_file(void)
{
    const char *path = tu_scratch("atomic.bin");
    brt_atomic_file f;
    brt_error err;
    size_t size = 0;
    unsigned char *back;
    CHECK(brt_atomic_open(&f, path, &err) == BRT_OK, "%s", err.message);
    CHECK(write(f.fd, "abc", 3) == 3, "write failed");
    EXPECT(!tu_file_exists(path), "the file has its name before it is complete");
    EXPECT(brt_atomic_close(&f, BRT_EIO, &err) == BRT_EIO, "a failure was not passed on");
    EXPECT(!tu_file_exists(path) && !tu_temporary_file_left(), "a failed write left a file");
    CHECK(brt_atomic_open(&f, path, &err) == BRT_OK, "%s", err.message);
    CHECK(write(f.fd, "abc", 3) == 3, "write failed");
    EXPECT(brt_atomic_close(&f, BRT_OK, &err) == BRT_OK, "%s", err.message);
    back = tu_slurp(path, &size);
    EXPECT(back && size == 3 && memcmp(back, "abc", 3) == 0, "the file does not hold what was written");
    EXPECT(!tu_temporary_file_left(), "the temporary file is left");
    free(back);
    EXPECT(brt_atomic_open(&f, tu_scratch("no/such/dir/x.bin"), &err) == BRT_EIO &&
               strstr(err.message, "cannot create"), "a missing folder: %s", err.message);
    EXPECT(brt_atomic_close(&f, BRT_EIO, &err) == BRT_EIO, "closing a failed open");
    remove(path);
}

static void test_io_stats_json(void)
{
    static const char *const fields[] = {"\"rays\": 18446744073709551615,",
                                         "\"batching_points\": 2,",
                                         "\"geometry_bytes\": 9007199254740993,",
                                         "\"disk_bytes_read\": 4,",
                                         "\"batch_loads\": 5,",
                                         "\"cache_peak_bytes\": 6,",
                                         "\"memory_limit\": 7,",
                                         "\"proxy_bytes\": 8,",
                                         "\"proxy_tests\": 9,",
                                         "\"proxy_culled\": 10,",
                                         "\"queued_visits\": 11,",
                                         "\"oversized_loads\": 12,",
                                         "\"visits\": 13,", "\"resident_visits\": 14,",
                                         "\"occlusion_rays\": 15,", "\"occlusion_hits\": 16,",
                                         "\"occlusion_batch_loads\": 17,", "\"occlusion_disk_bytes_read\": 18,",
                                         "\"peak_rss_bytes\": 19,", "\"occlusion_inner_stopped\": 20,",
                                         "\"prototype_loads\": 21,", "\"decoded_bytes\": 22,",
                                         "\"load_seconds\": 0.125,",
                                         "\"seconds\": 1.5,",
                                         "\"build_seconds\": 0.25,",
                                         "\"bvh_bytes_per_triangle\": 40,",
                                         "\"mrays_per_second\": null\n}\n"};
    brt_stats s;
    memset(&s, 0, sizeof s);
    s.rays = UINT64_MAX;
    s.batching_points = 2;
    s.geometry_bytes = 9007199254740993ull; /* 2^53 + 1: not a double */
    s.disk_bytes_read = 4;
    s.batch_loads = 5;
    s.cache_peak_bytes = 6;
    s.memory_limit = 7;
    s.proxy_bytes = 8;
    s.proxy_tests = 9;
    s.proxy_culled = 10;
    s.queued_visits = 11;
    s.oversized_loads = 12;
    s.visits = 13;
    s.resident_visits = 14;
    s.occlusion_rays = 15;
    s.occlusion_hits = 16;
    s.occlusion_batch_loads = 17;
    s.occlusion_disk_bytes_read = 18;
    s.peak_rss_bytes = 19;
    s.occlusion_inner_stopped = 20;
    s.prototype_loads = 21;
    s.decoded_bytes = 22;
    s.load_seconds = 0.125;
    s.seconds = 1.5;
    s.build_seconds = 0.25;
    s.bvh_bytes_per_triangle = 40.0;
    s.mrays_per_second = INFINITY; /* JSON has no inf: null */
    const char *path = scratch_path("stats.json");
    brt_error err;
    size_t size = 0, i;
    char *text;
    CHECK(brt_stats_write_json(path, &s, &err) == BRT_OK, "%s", err.message);
    text = (char *)tu_slurp(path, &size);
    CHECK(text, "cannot read %s", path);
    text[size] = 0;
    EXPECT(text[0] == '{', "not an object: %s", text);
    for (i = 0; i < sizeof fields / sizeof fields[0]; i++)
        EXPECT(strstr(text, fields[i]), "'%s' missing in:\n%s", fields[i], text);
    free(text);
}

/* A program's statistics (ex_stats_write) are the library's object with
** its own fields added before the closing brace, byte for byte, and the
** library's object alone when it has none. */
static void test_program_stats_json(void)
{
    brt_stats s;
    char lib[BRT_STATS_JSON_BYTES + 64], *text;
    size_t used;
    brt_error err;
    const char *path = scratch_path("program.json");
    memset(&s, 0, sizeof s);
    s.rays = 3;
    s.mrays_per_second = 0;   /* the shortest last value: one character */
    used = brt_stats_format_json(&s, lib);
    CHECK(used > 3 && strcmp(lib + used - 3, "\n}\n") == 0, "the library's object does not end \"\\n}\\n\"");
    CHECK(ex_stats_write(path, &s, "", &err) == BRT_OK, "%s", err.message);
    text = (char *)tu_slurp(path, NULL);
    EXPECT(text && strcmp(text, lib) == 0, "no fields of its own, but not the library's object:\n%s", text ? text : "");
    free(text);
    CHECK(ex_stats_write(path, &s, "  \"spp\": 4", &err) == BRT_OK, "%s", err.message);
    text = (char *)tu_slurp(path, NULL);
    snprintf(lib + used - 3, sizeof lib - (used - 3), ",\n  \"spp\": 4\n}\n");
    EXPECT(text && strcmp(text, lib) == 0, "the program's fields not spliced before the brace:\n%s", text ? text : "");
    free(text);
}

void suite_mesh(void)
{
    test_run("mesh: obj face syntaxes", test_obj_face_syntaxes);
    test_run("mesh: obj negative indices", test_obj_negative_indices);
    test_run("mesh: obj polygon fans", test_obj_fans);
    test_run("mesh: obj ignored statements, crlf", test_obj_ignored_statements_and_crlf);
    test_run("mesh: obj degenerate triangles kept", test_obj_degenerate_kept);
    test_run("mesh: obj numbers equal strtof", test_obj_numbers_match_strtof);
    test_run("mesh: obj streaming across chunks", test_obj_streaming_across_chunks);
    test_run("mesh: obj garbage", test_obj_garbage);
    test_run("mesh: obj missing coordinates", test_obj_missing_coordinates);
    test_run("mesh: obj non-finite coordinates", test_obj_non_finite);
    test_run("mesh: obj index out of range", test_obj_index_out_of_range);
    test_run("mesh: obj face with fewer than 3 vertices", test_obj_short_face);
    test_run("mesh: obj no triangles", test_obj_no_triangles);
    test_run("mesh: obj every prefix", test_obj_every_prefix);
    test_run("mesh: an error's place far into the file, and its first occurrence", test_error_place_far_and_twice);
    test_run("mesh: format by content", test_format_by_content);
    test_run("mesh: missing file", test_missing_file);
    test_run("mesh: ply all flavours equal obj", test_ply_all_flavours_match_obj);
    test_run("mesh: ply ascii details", test_ply_ascii_details);
    test_run("mesh: ply streaming across chunks", test_ply_streaming_across_chunks);
    test_run("mesh: ply bad header", test_ply_bad_header);
    test_run("mesh: ply ascii bad values", test_ply_ascii_bad_values);
    test_run("mesh: ply non-finite coordinates", test_ply_non_finite);
    test_run("mesh: ply index out of range", test_ply_index_out_of_range);
    test_run("mesh: ply face with fewer than 3 vertices", test_ply_short_face);
    test_run("mesh: ply truncated, no triangles", test_ply_truncated_and_empty);
    test_run("mesh: ply binary errors by element", test_ply_binary_errors);
    test_run("mesh: fuzzed obj and ply", test_ply_obj_fuzz);
    test_run("mesh: shared bunny_tiny", test_shared_bunny_tiny);
    test_run("mesh: shared bunny", test_shared_bunny);
    test_run("mesh: bounds", test_mesh_bounds);
    test_run("io: rays round trip", test_io_rays_round_trip);
    test_run("io: hits round trip", test_io_hits_round_trip);
    test_run("io: record size not a multiple", test_io_bad_sizes);
    test_run("io: empty and missing files", test_io_empty_and_missing);
    test_run("io: write into missing directory", test_io_write_into_missing_directory);
    test_run("io: parse size", test_io_parse_size);
    test_run("io: one of each utility", test_io_utilities);
    test_run("io: atomic file", test_io_atomic_file);
    test_run("io: stats json", test_io_stats_json);
    test_run("io: a program's stats: the library's object, its fields before the brace", test_program_stats_json);
}
