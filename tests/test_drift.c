/*
** tests/test_drift.c -- the drift check (issue 40, item 6): what the
** README and the comments say, held against what the tree holds.
**
** 1. Every identifier a comment or the README names exists.  A CITATION
**    is, in the README, a code span (`...`, fenced blocks aside) that is
**    one identifier, `name()`, or `type_name.field`; in a comment of the
**    core (*.c, *.h at the top) or of examples/ (every folder), a word
**    written as code is: snake_case with an underscore
**    ([a-z][a-z0-9]*_[a-z0-9_]+), a macro ([A-Z][A-Z0-9]*_[A-Z0-9_]+), or
**    brt_, BRT_, ex_ anything.  Not citations: parts of a path
**    (tests/test_policy.c: after a '/', before '/' or a file extension),
**    parts of an option (after or before '-'), and math subscripts (the
**    part after the last '_' is one or two of i j k a b s x y z: p_i,
**    C_ij, t_X).  A name broken at the end of a comment line
**    (brt_instance_ / reach) is joined with the next line's first word;
**    brt_mesh_parse_* stands for every name it starts.  A citation must
**    be a word of the tree's code (comments removed, strings kept: a
**    function, macro, type, field, option, statistics field or make
**    variable): every *.c and *.h of the top, examples/ and tests/ (this
**    file aside: its lists name what does not exist) and the Makefile
**    (its # comments removed).  ALLOWED lists the words that are not the
**    tree's names, each with its reason.
** 2. Every program answers --help with exit 0 and a usage line: "cli:
**    --help of every program" (tests/test_cli.c) holds it, for every
**    program of examples/ (embree_trace and mpi_trace: their suites).
** 3. Every option of a README command line exists: in an indented code
**    line or a code span, a command is `build/PROG ...` or
**    `./build/PROG ...` anywhere, `PROG ...` at the start of a code span
**    (PROG a program of examples/), or `make ...`; it ends at "&&", ";",
**    an unescaped "|" or "#".  Each --option of a program must be in its
**    --help (an optional program not built, embree_trace without Embree:
**    in its source or the tracers' shared parser, examples/lib/tracer.c);
**    each target of make must be a rule of the Makefile, each VAR= a
**    variable it reads ($(VAR)).
** 4. The README's example outputs are what the commands print:
**    - the commands of an indented block followed by a fenced block (the
**      reader's path: trace --follow 31) run in a fresh folder, and the
**      last one's standard output is the fenced block, line for line,
**      nothing masked (the journey is deterministic: one thread);
**    - the error example of "Programs" (`trace: mesh.obj:12: ...`) is
**      what trace says of a mesh whose line 12 names vertex 9 of 8 (the
**      README shows the message, not the mesh: the test writes one);
**    - make demo's table (too slow for make test, 15 s: "drift long:",
**      make test-long): disk MiB, loads, visits/spp, culled and "same
**      image" are deterministic and compared; the columns time s, load s
**      and Mrays/s and the summary's "time x" are wall times and masked.
**    Not reproduced: the tables of make figures, bench-paper,
**    bench-inner, bench-threads, bench-mpi, bench-embree and bench-pbrt
**    (minutes each, and most of their numbers are timings of one
**    machine), make test's own last line, and the forged scene file's
**    message in "The scene file" (it needs a file forged byte by byte:
**    tests/test_hardening.c forges them).
*/
#include "test.h"
#include "util.h"

#include <ctype.h>
#include <dirent.h>
#include <errno.h>
#include <limits.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* Words that are not the tree's names, and why. */
static const struct { const char *word, *reason; } ALLOWED[] = {
    {"octant_mask", "ESVO's variable (Laine and Karras, Raycast.inl), mapped to ours in svdag.c"},
    {"tx_coef", "ESVO's variable, mapped to ours in svdag.c"},
    {"tx_bias", "ESVO's variable, mapped to ours in svdag.c"},
    {"step_mask", "ESVO's variable, mapped to ours in svdag.c"},
    {"l_start", "POSIX struct flock's field, zeroed by memset (batchrt.c)"},
    {"l_len", "POSIX struct flock's field, zeroed by memset (batchrt.c)"},
    {"COUNT_TYPE", "a placeholder of the PLY header's grammar (property list COUNT_TYPE ITEM_TYPE NAME)"},
    {"ITEM_TYPE", "a placeholder of the PLY header's grammar"},
    {"FLOAT3X4_ROW_MAJOR", "Embree's matrix layout (RTC_FORMAT_FLOAT3X4_ROW_MAJOR), named as Embree's"},
    {"SQLITE_TEST", "SQLite's macro, testing.h's model"},
    {"u16", "the README's notation for file fields (as u32, u64), not a C type"},
    {"nlevels", "a pbrt-v4 parameter the reader skips by not knowing it"},
    {"LICENSE", "a file of the repository"},
};

/* ===================================================================== */
/* A set of words                                                        */
/* ===================================================================== */

typedef struct word_set {
    char **slot;
    size_t cap, count;
} word_set;

static size_t word_hash(const char *w, size_t n)
{
    size_t h = 2166136261u, i;
    for (i = 0; i < n; i++) h = (h ^ (unsigned char)w[i]) * 16777619u;
    return h;
}

/* The slot of w, or of the empty slot where it would go. */
static size_t word_slot(const word_set *s, const char *w, size_t n)
{
    size_t i = word_hash(w, n) & (s->cap - 1);
    while (s->slot[i] && !(strncmp(s->slot[i], w, n) == 0 && s->slot[i][n] == 0)) i = (i + 1) & (s->cap - 1);
    return i;
}

static int set_has(const word_set *s, const char *w, size_t n)
{
    return s->cap && s->slot[word_slot(s, w, n)] != NULL;
}

/* 1 when some word of the set starts with the n bytes at w. */
static int set_has_prefix(const word_set *s, const char *w, size_t n)
{
    size_t i;
    for (i = 0; i < s->cap; i++)
        if (s->slot[i] && strncmp(s->slot[i], w, n) == 0 && s->slot[i][n]) return 1;
    return 0;
}

static int set_grow(word_set *s)
{
    word_set bigger;
    size_t i;
    bigger.cap = s->cap ? 2 * s->cap : 4096;
    bigger.count = s->count;
    bigger.slot = calloc(bigger.cap, sizeof *bigger.slot);
    if (!bigger.slot) return 0;
    for (i = 0; i < s->cap; i++)
        if (s->slot[i]) bigger.slot[word_slot(&bigger, s->slot[i], strlen(s->slot[i]))] = s->slot[i];
    free(s->slot);
    *s = bigger;
    return 1;
}

static void set_add(word_set *s, const char *w, size_t n)
{
    size_t i;
    if (2 * (s->count + 1) > s->cap && !set_grow(s)) return;
    i = word_slot(s, w, n);
    if (s->slot[i] || !(s->slot[i] = malloc(n + 1))) return;
    memcpy(s->slot[i], w, n);
    s->slot[i][n] = 0;
    s->count++;
}

static void set_free(word_set *s)
{
    size_t i;
    for (i = 0; i < s->cap; i++) free(s->slot[i]);
    free(s->slot);
    memset(s, 0, sizeof *s);
}

/* ===================================================================== */
/* Reading the tree                                                      */
/* ===================================================================== */

static int is_word_char(char c)
{
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_';
}

static size_t word_length(const char *p)
{
    size_t n = 0;
    while (is_word_char(p[n])) n++;
    return n;
}

static int has_suffix(const char *s, const char *suffix)
{
    size_t n = strlen(s), k = strlen(suffix);
    return n >= k && strcmp(s + n - k, suffix) == 0;
}

/* Calls fn for every *.c and *.h under dir (into subfolders when deep). */
static void each_source(const char *dir, int deep, void (*fn)(const char *path, void *user), void *user)
{
    DIR *d = opendir(dir);
    struct dirent *e;
    if (!d) return;
    while ((e = readdir(d)) != NULL) {
        char path[1024];
        struct stat st;
        if (e->d_name[0] == '.') continue;
        snprintf(path, sizeof path, "%s/%s", dir, e->d_name);
        if (stat(path, &st) != 0) continue;
        if (S_ISDIR(st.st_mode)) {
            if (deep) each_source(path, deep, fn, user);
        } else if (has_suffix(e->d_name, ".c") || has_suffix(e->d_name, ".h")) {
            fn(path[0] == '.' && path[1] == '/' ? path + 2 : path, user);
        }
    }
    closedir(d);
}

/* Splits C text in place into code (comments blanked, strings kept) and
** notes (all but the comments blanked); both keep every newline. */
static void split_c(char *code, char *notes)
{
    size_t i = 0, n = strlen(code);
    memset(notes, ' ', n);
    notes[n] = 0;
    while (i < n) {
        size_t j = i;
        if (code[i] == '/' && (code[i + 1] == '*' || code[i + 1] == '/')) {
            const char *end = code[i + 1] == '*' ? strstr(code + i + 2, "*/") : strchr(code + i, '\n');
            j = end ? (size_t)(end - code) + (code[i + 1] == '*' ? 2 : 0) : n;
            for (; i < j; i++)
                if (code[i] != '\n') notes[i] = code[i], code[i] = ' ';
                else notes[i] = '\n';
            continue;
        }
        if (code[i] == '"' || code[i] == '\'') {
            for (j = i + 1; j < n && code[j] != code[i] && code[j] != '\n'; j++)
                if (code[j] == '\\') j++;
        } else if (code[i] == '\n') {
            notes[i] = '\n';
        }
        i = j + 1;
    }
}

/* Every word of text into s. */
static void add_words(word_set *s, const char *text)
{
    while (*text) {
        size_t n = word_length(text);
        if (n) set_add(s, text, n), text += n;
        else text++;
    }
}

static void add_code_words(const char *path, void *user)
{
    char *code, *notes;
    if (strcmp(path, "tests/test_drift.c") == 0) return;
    code = (char *)tu_slurp(path, NULL);
    notes = code ? malloc(strlen(code) + 1) : NULL;
    if (notes) {
        split_c(code, notes);
        add_words(user, code);
    }
    free(code);
    free(notes);
}

/* The Makefile without its comments (a '#' to the end of its line). */
static char *makefile_code(void)
{
    char *text = (char *)tu_slurp("Makefile", NULL), *p;
    for (p = text; p && *p; p++)
        if (*p == '#')
            while (*p && *p != '\n') *p++ = ' ';
    return text;
}

/* Every word of the tree's code (see the top of this file). */
static int code_words(word_set *s)
{
    char *make = makefile_code();
    memset(s, 0, sizeof *s);
    each_source(".", 0, add_code_words, s);
    each_source("examples", 1, add_code_words, s);
    each_source("tests", 1, add_code_words, s);
    if (make) add_words(s, make);
    free(make);
    return make != NULL && s->count > 1000;
}

/* The README with its fenced blocks blanked (their lines kept). */
static char *readme_prose(void)
{
    char *text = (char *)tu_slurp("README.md", NULL), *p = text;
    int fenced = 0;
    while (p && *p) {
        char *eol = strchr(p, '\n');
        size_t n = eol ? (size_t)(eol - p) : strlen(p);
        int fence = strncmp(p, "```", 3) == 0;
        if (fence || fenced) memset(p, ' ', n);
        fenced ^= fence;
        p += n + (eol != NULL);
    }
    return text;
}

static int line_of(const char *text, const char *at)
{
    int line = 1;
    for (; text < at; text++) line += *text == '\n';
    return line;
}

/* The build folder as an absolute path (the commands run elsewhere). */
static const char *build_dir(void)
{
    static char path[PATH_MAX + 64];
    const char *build = getenv("BRT_BUILD") ? getenv("BRT_BUILD") : "build";
    char cwd[PATH_MAX];
    if (build[0] == '/' || !getcwd(cwd, sizeof cwd)) snprintf(path, sizeof path, "%s", build);
    else snprintf(path, sizeof path, "%s/%s", cwd, build);
    return path;
}

/* ===================================================================== */
/* 1. Every identifier a comment or the README names exists              */
/* ===================================================================== */

typedef struct citations {
    word_set words;
    int found;          /* citations checked */
} citations;

static int allowed(const char *w, size_t n)
{
    size_t i;
    for (i = 0; i < sizeof ALLOWED / sizeof ALLOWED[0]; i++)
        if (strlen(ALLOWED[i].word) == n && strncmp(ALLOWED[i].word, w, n) == 0) return 1;
    return 0;
}

/* Checks one citation of file at line: a wildcard (brt_mesh_parse_*)
** needs a word it starts. */
static void check_citation(citations *c, const char *file, int line, const char *w, size_t n, int wildcard)
{
    c->found++;
    if (wildcard ? set_has_prefix(&c->words, w, n) : set_has(&c->words, w, n) || allowed(w, n)) return;
    test_fail_at(__FILE__, __LINE__, "%s:%d: `%.*s%s` names nothing in the tree (no function, macro, type, "
                 "field, option or string): rename it to the real name", file, line, (int)n, w,
                 wildcard ? "*" : "");
}

/* 1 when the word is written as code (the top of this file). */
static int looks_cited(const char *w, size_t n)
{
    size_t i, last = n, lower = 0, upper = 0;
    if (n > 4 && (strncmp(w, "brt_", 4) == 0 || strncmp(w, "BRT_", 4) == 0)) return 1;
    if (n > 3 && strncmp(w, "ex_", 3) == 0) return 1;
    while (last > 0 && w[last - 1] != '_') last--;      /* w + last: after the last '_' */
    if (last < 2 || last == n) return 0;
    if (n - last <= 2 && strspn(w + last, "ijkabsxyzIJKABSXYZ") >= n - last) return 0;   /* a subscript */
    for (i = 0; i < n; i++) {
        lower += w[i] >= 'a' && w[i] <= 'z';
        upper += w[i] >= 'A' && w[i] <= 'Z';
    }
    return ((w[0] >= 'a' && w[0] <= 'z') || (w[0] >= 'A' && w[0] <= 'Z')) && (lower == 0) != (upper == 0);
}

/* A file name's extension follows (".c", ".json"): 1 to 4 lowercase
** letters after a '.', then no word character. */
static int extension_follows(const char *p)
{
    size_t k = 0;
    if (*p != '.') return 0;
    while (p[1 + k] >= 'a' && p[1 + k] <= 'z') k++;
    return k >= 1 && k <= 4 && !is_word_char(p[1 + k]);
}

/* The word that continues a name broken after its '_' at a line's end
** ("brt_instance_" / "** reach"), or NULL. */
static const char *continuation(const char *p)
{
    const char *q = p;
    while (*q == ' ' || *q == '\t') q++;
    if (*q != '\n') return NULL;
    q++;
    while (*q == ' ' || *q == '\t' || *q == '*' || *q == '/') q++;
    return is_word_char(*q) ? q : NULL;
}

/* Checks the citations in the comments (notes) of file. */
static void check_notes(citations *c, const char *file, const char *notes)
{
    const char *p = notes;
    while (*p) {
        size_t n = word_length(p);
        char joined[256];
        const char *next;
        if (!n) { p++; continue; }
        if (p[n - 1] == '_' && (next = continuation(p + n)) != NULL && n + word_length(next) < sizeof joined) {
            snprintf(joined, sizeof joined, "%.*s%.*s", (int)n, p, (int)word_length(next), next);
            if (looks_cited(joined, strlen(joined)))
                check_citation(c, file, line_of(notes, p), joined, strlen(joined), 0);
        } else if (looks_cited(p, n) && !(p > notes && (p[-1] == '/' || p[-1] == '-')) && p[n] != '/' &&
                   p[n] != '-' && !extension_follows(p + n)) {
            check_citation(c, file, line_of(notes, p), p, n, p[n - 1] == '_' && p[n] == '*');
        }
        p += n;
    }
}

static void check_source_notes(const char *path, void *user)
{
    char *code = (char *)tu_slurp(path, NULL), *notes = code ? malloc(strlen(code) + 1) : NULL;
    if (notes) {
        split_c(code, notes);
        check_notes(user, path, notes);
    }
    free(code);
    free(notes);
}

/* The code spans of the README's prose (between backquotes; a span may
** run over a line's end): fn(span, length, line). */
static void each_span(const char *prose, void (*fn)(const char *span, size_t n, int line, void *user), void *user)
{
    const char *p = prose;
    while ((p = strchr(p, '`')) != NULL) {
        const char *end = strchr(p + 1, '`');
        if (!end) break;
        fn(p + 1, (size_t)(end - p - 1), line_of(prose, p), user);
        p = end + 1;
    }
}

/* A README span that is one identifier, name(), or type_name.field (a
** '_' before the first '.', and no file extension after the last: a file
** name is neither): each of its names checked. */
static void check_span(const char *span, size_t n, int line, void *user)
{
    size_t first = word_length(span), k = first, last = n;
    if (!first || (span[0] >= '0' && span[0] <= '9')) return;
    if (first + 2 == n && span[first] == '(' && span[first + 1] == ')') n = first;
    while (k < n && span[k] == '.' && is_word_char(span[k + 1])) k += 1 + word_length(span + k + 1);
    if (k != n) return;                                 /* not names alone */
    while (last > 0 && span[last - 1] != '.') last--;
    if (first < n && (!memchr(span, '_', first) || extension_follows(span + last - 1))) return;
    for (k = 0; k < n; k += word_length(span + k) + 1)
        check_citation(user, "README.md", line, span + k, word_length(span + k), 0);
}

static void test_identifiers_exist(void)
{
    citations c;
    char *prose = readme_prose();
    memset(&c, 0, sizeof c);
    CHECK(prose, "cannot read README.md (run from the repository's top)");
    CHECK(code_words(&c.words), "cannot read the tree's sources and Makefile");
    each_source(".", 0, check_source_notes, &c);
    each_source("examples", 1, check_source_notes, &c);
    each_span(prose, check_span, &c);
    EXPECT(c.found > 1000, "only %d citations found: the scanner is broken", c.found);
    set_free(&c.words);
    free(prose);
}

/* ===================================================================== */
/* 3. Every option of a README command line exists                       */
/* ===================================================================== */

/* 1 when examples/KIND/name.c is a program (tutorials, tools, bench). */
static int is_program(const char *name, size_t n)
{
    static const char *const kinds[] = {"tutorials", "tools", "bench"};
    size_t i;
    char path[512];
    for (i = 0; n < 128 && i < sizeof kinds / sizeof *kinds; i++) {
        snprintf(path, sizeof path, "examples/%s/%.*s.c", kinds[i], (int)n, name);
        if (tu_file_exists(path)) return 1;
    }
    return 0;
}

/* a, a newline and b, in a new string (NULL when either is). */
static char *joined_text(const char *a, const char *b)
{
    char *text = a && b ? malloc(strlen(a) + strlen(b) + 2) : NULL;
    if (text) sprintf(text, "%s\n%s", a, b);
    return text;
}

/* What the check of the README's commands keeps: each program's options
** text, the Makefile, and how many words it checked. */
#define MAX_PROGRAMS 32
typedef struct commands {
    char name[MAX_PROGRAMS][64];
    char *options[MAX_PROGRAMS];
    int programs, checked;
    char *makefile;
} commands;

/* What knows a program's options: its --help (stdout and stderr), or,
** not built (make embree), its source and the tracers' shared parser. */
static const char *options_text(commands *k, const char *prog)
{
    char path[PATH_MAX + 256], *a, *b;
    int i;
    for (i = 0; i < k->programs; i++)
        if (strcmp(k->name[i], prog) == 0) return k->options[i];
    if (k->programs == MAX_PROGRAMS || strlen(prog) >= sizeof k->name[0]) return NULL;
    snprintf(path, sizeof path, "%s/%s", build_dir(), prog);
    if (tu_file_exists(path)) {
        tu_run("%s --help", prog);
        a = tu_last_stdout();
        b = tu_last_stderr();
    } else {
        snprintf(path, sizeof path, "examples/tools/%s.c", prog);
        a = (char *)tu_slurp(path, NULL);
        b = (char *)tu_slurp("examples/lib/tracer.c", NULL);
    }
    snprintf(k->name[k->programs], sizeof k->name[0], "%s", prog);
    k->options[k->programs] = joined_text(a, b);
    free(a);
    free(b);
    return k->options[k->programs++];
}

/* 1 when text holds the option (its "--" included) as a whole word. */
static int holds_option(const char *text, const char *opt)
{
    const char *p = text;
    size_t n = strlen(opt);
    for (; (p = strstr(p, opt)) != NULL; p++)
        if (!is_word_char(p[n]) && p[n] != '-') return 1;
    return 0;
}

/* The words of one command, up to its end (&&, ;, an unescaped |, #). */
typedef struct command {
    char word[48][128];
    int count;
} command;

static const char *read_command(const char *p, const char *end, command *cmd)
{
    cmd->count = 0;
    while (p < end) {
        size_t n = 0;
        while (p < end && (*p == ' ' || *p == '\n' || *p == '[' || *p == ']')) p++;
        if (p >= end) break;
        if (*p == '#' || *p == ';' || (*p == '|' && p[-1] != '\\') || (*p == '&' && p[1] == '&'))
            return *p == '#' ? end : p + 1 + (*p == '&');
        while (p + n < end && p[n] != ' ' && p[n] != '\n' && p[n] != ']' && p[n] != ';') n++;
        if (cmd->count < 48 && n < 128) snprintf(cmd->word[cmd->count++], 128, "%.*s", (int)n, p);
        p += n;
    }
    return end;
}

/* Each --option of build/PROG's words from `from` on. */
static void check_program_options(commands *k, const command *cmd, int from, const char *prog, int line)
{
    const char *text = options_text(k, prog);
    int i;
    if (!text) {
        test_fail_at(__FILE__, __LINE__, "README.md:%d: cannot learn %s's options", line, prog);
        return;
    }
    for (i = from; i < cmd->count; i++) {
        const char *w = cmd->word[i];
        char opt[128];
        size_t n = 2;
        if (strncmp(w, "--", 2) != 0) continue;
        while (is_word_char(w[n]) || w[n] == '-') n++;
        snprintf(opt, sizeof opt, "%.*s", (int)n, w);
        k->checked += n > 2;
        if (n > 2 && !holds_option(text, opt))
            test_fail_at(__FILE__, __LINE__, "README.md:%d: %s %s: no such option in %s --help", line, prog, opt,
                         prog);
    }
}

/* 1 when the Makefile has a rule for target. */
static int make_rule(const char *makefile, const char *target)
{
    const char *p = makefile;
    size_t n = strlen(target);
    while (p && *p) {
        const char *eol = strchr(p, '\n'), *colon = strchr(p, ':'), *q = p;
        if (!eol) eol = p + strlen(p);
        if (*p != '\t' && colon && colon < eol && colon[1] != '=')
            while ((q = strstr(q, target)) != NULL && q < colon) {
                if ((q == p || q[-1] == ' ') && (q[n] == ' ' || q[n] == ':')) return 1;
                q += n;
            }
        p = *eol ? eol + 1 : eol;
    }
    return 0;
}

/* make's targets and VAR=value words (a quoted value may hold blanks). */
static void check_make(commands *k, const command *cmd, int line)
{
    const char *makefile = k->makefile;
    int i;
    for (i = 1; i < cmd->count; i++) {
        const char *w = cmd->word[i], *eq = strchr(w, '=');
        char var[160];
        k->checked++;
        if (eq) {
            snprintf(var, sizeof var, "$(%.*s)", (int)(eq - w), w);
            if (!strstr(makefile, var))
                test_fail_at(__FILE__, __LINE__, "README.md:%d: make %.*s=: the Makefile reads no %s", line,
                             (int)(eq - w), w, var);
            if (eq[1] == '"')
                while (i + 1 < cmd->count && !has_suffix(cmd->word[i], "\"")) i++;
        } else if (w[0] >= 'a' && w[0] <= 'z' && !make_rule(makefile, w)) {
            test_fail_at(__FILE__, __LINE__, "README.md:%d: make %s: no such target in the Makefile", line, w);
        }
    }
}

/* The commands of one piece of README text (a code line or a span). */
static void check_piece(commands *k, const char *p, size_t n, int line, int span)
{
    const char *end = p + n;
    command cmd;
    while (p < end) {
        int i;
        p = read_command(p, end, &cmd);
        if (cmd.count && strcmp(cmd.word[0], "make") == 0) check_make(k, &cmd, line);
        for (i = 0; i < cmd.count; i++) {
            const char *w = cmd.word[i];
            const char *prog = strncmp(w, "build/", 6) == 0 ? w + 6 : strncmp(w, "./build/", 8) == 0 ? w + 8
                             : span && i == 0 ? w : NULL;
            if (prog && is_program(prog, strlen(prog))) {
                check_program_options(k, &cmd, i + 1, prog, line);
                break;
            }
        }
        span = 0;
    }
}

static void check_span_commands(const char *span, size_t n, int line, void *user)
{
    check_piece(user, span, n, line, 1);
}

static void test_options_exist(void)
{
    char *prose = readme_prose();
    const char *p = prose;
    commands k;
    int i;
    memset(&k, 0, sizeof k);
    k.makefile = makefile_code();
    CHECK(prose && k.makefile, "cannot read README.md and the Makefile (run from the repository's top)");
    while (*p) {
        const char *eol = strchr(p, '\n');
        size_t n = eol ? (size_t)(eol - p) : strlen(p);
        if (strncmp(p, "    ", 4) == 0) check_piece(&k, p, n, line_of(prose, p), 0);
        p += n + (eol != NULL);
    }
    each_span(prose, check_span_commands, &k);
    EXPECT(k.checked > 100, "only %d options and make words found in README.md's commands: the scanner is broken",
           k.checked);
    for (i = 0; i < k.programs; i++) free(k.options[i]);
    free(k.makefile);
    free(prose);
}

/* ===================================================================== */
/* 4. The README's example outputs are what the commands print           */
/* ===================================================================== */

/* Runs the README's command line in dir, its scene files kept there;
** build/ means the build folder.  The exit status; its output in cli.out
** and cli.err of the scratch folder. */
static int run_in(const char *dir, const char *line)
{
    char head[PATH_MAX * 2 + 64], args[4096];
    while (*line == ' ') line++;
    snprintf(head, sizeof head, "cd '%s' && BRT_SCENE_DIR='%s' ", dir, dir);
    if (strncmp(line, "build/", 6) == 0) snprintf(args, sizeof args, "'%s/'%s", build_dir(), line + 6);
    else snprintf(args, sizeof args, "%s", line);
    return tu_shell(head, args, "");
}

/* Compares the lines of shown (the README's, from its line first) with
** those of printed; names the first difference. */
static void compare_lines(const char *shown, const char *printed, int first, const char *what)
{
    int line = first;
    while (*shown || *printed) {
        size_t a = strcspn(shown, "\n"), b = strcspn(printed, "\n");
        if (a != b || strncmp(shown, printed, a) != 0) {
            test_fail_at(__FILE__, __LINE__, "README.md:%d: shows '%.*s', %s prints '%.*s'", line, (int)a, shown,
                         what, (int)b, printed);
            return;
        }
        shown += a + (shown[a] == '\n');
        printed += b + (printed[b] == '\n');
        line++;
    }
}

/* One example: the indented commands of lines [cmds, cmds_end) and the
** fenced block's text out (its lines from out_line). */
static void check_example(const char *cmds, const char *cmds_end, const char *out, int out_line, int number)
{
    char dir[1024], last[4096] = "";
    char *printed;
    snprintf(dir, sizeof dir, "%s/drift-example-%d", test_tmpdir(), number);
    if (mkdir(dir, 0755) != 0 && errno != EEXIST) {
        test_fail_at(__FILE__, __LINE__, "cannot create %s", dir);
        return;
    }
    while (cmds < cmds_end) {
        size_t n = strcspn(cmds, "\n");
        size_t blank = strspn(cmds, " ");
        snprintf(last, sizeof last, "%.*s", (int)(n - blank), cmds + blank);
        if (run_in(dir, last) != 0) {
            test_fail_at(__FILE__, __LINE__, "README.md: `%s` failed in %s", last, dir);
            return;
        }
        cmds += n + 1;
    }
    printed = tu_last_stdout();
    compare_lines(out, printed ? printed : "", out_line, last);
    free(printed);
}

/* Every indented block of commands followed by a fenced block: how many. */
static int check_examples(char *readme)
{
    char *p = readme;
    int count = 0;
    while ((p = strstr(p, "\n```\n")) != NULL) {
        char *out = p + 5, *close = strstr(out, "\n```"), *start = p, *before;
        if (!close) break;
        while (start > readme && start[-1] == '\n') start--;   /* blank lines */
        for (before = start; before > readme;) {
            char *bol = before - 1;
            while (bol > readme && bol[-1] != '\n') bol--;
            if (strncmp(bol, "    ", 4) != 0) break;
            before = bol;
        }
        if (before < start) {
            close[1] = 0;
            check_example(before, start, out, line_of(readme, out), ++count);
            close[1] = '`';
        }
        p = close + 1;
    }
    return count;
}

/* README, "Programs": the one-line error's example is trace's message for
** a mesh whose line 12 names vertex 9 of 8. */
static void check_error_example(const char *readme)
{
    const char *span = strstr(readme, "`trace: mesh.obj:12: ");
    size_t n;
    char *err, dir[1024];
    int status;
    CHECK(span, "README.md: the error example `trace: mesh.obj:12: ...` is gone: update this test");
    n = strcspn(span + 1, "`");
    snprintf(dir, sizeof dir, "%s/drift-error", test_tmpdir());
    CHECK(mkdir(dir, 0755) == 0 || errno == EEXIST, "cannot create %s", dir);
    tu_put("drift-error/mesh.obj", "# a mesh whose line 12 names a vertex it does not have\n"
           "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\nf 1 2 3\nf 1 3 4\nf 1 2 9\n");
    tu_put("drift-error/rays.rays", "");
    status = run_in(dir, "build/trace mesh.obj rays.rays hits.hits");
    err = tu_last_stderr();
    EXPECT(status == 1, "trace on a bad mesh: exit status %d", status);
    if (err) err[strcspn(err, "\n")] = 0;
    if (!err || strlen(err) != n || strncmp(err, span + 1, n) != 0)
        test_fail_at(__FILE__, __LINE__, "README.md:%d: shows '%.*s', trace prints '%s'", line_of(readme, span),
                     (int)n, span + 1, err ? err : "");
    free(err);
}

static void test_example_outputs(void)
{
    char *readme = (char *)tu_slurp("README.md", NULL);
    CHECK(readme, "cannot read README.md (run from the repository's top)");
    EXPECT(check_examples(readme) >= 1, "README.md shows no command with its output (the reader's path's "
           "trace --follow): this test needs updating");
    check_error_example(readme);
    free(readme);
}

/* A copy of make demo's table and summary, from the line starting
** "| run   " (the threads' table has a "| run |") through the one holding
** "proxies: ", with the wall times masked: the cells of columns 6-8 (time
** s, load s, Mrays/s) become "#", the summary ends "time x#"; blank
** lines and backquotes dropped.  NULL when absent. */
static char *demo_table(const char *text)
{
    const char *p = strstr(text, "| run   "), *end = p ? strstr(p, "proxies: ") : NULL;
    char *copy, *q;
    if (!end) return NULL;
    end += strcspn(end, "\n");
    copy = q = malloc((size_t)(end - p) + 2);
    while (copy && p < end) {
        const char *eol = p + strcspn(p, "\n"), *t;
        int bar = 0;
        for (t = p; t < eol; t++) {
            bar += *t == '|';
            if (*t == '`' || (*p == '|' && bar >= 6 && bar <= 8 && *t != '|' && t[-1] != '|')) continue;
            *q++ = *p == '|' && bar >= 6 && bar <= 8 && *t != '|' ? '#' : *t;
            if (q - copy >= 6 && strncmp(q - 6, "time x", 6) == 0) {
                *q++ = '#';
                break;
            }
        }
        if (eol > p) *q++ = '\n';
        p = eol + (*eol == '\n');
    }
    if (copy) *q = 0;
    return copy;
}

/* make test-long: README, "make demo": the table and its summary line. */
static void test_demo_output(void)
{
    char *readme, *printed, *shown, *got;
    char args[PATH_MAX + 128];
    if (!getenv("BRT_TEST_LONG")) {
        test_skip("a long test: make test-long");
        return;
    }
    snprintf(args, sizeof args, "BRT_SCENE_DIR='@' make -s demo BUILD='%s'",
             getenv("BRT_BUILD") ? getenv("BRT_BUILD") : "build");
    CHECK(tu_shell("", args, "") == 0, "make demo failed");
    readme = (char *)tu_slurp("README.md", NULL);
    printed = tu_last_stdout();
    shown = readme ? demo_table(readme) : NULL;
    got = printed ? demo_table(printed) : NULL;
    EXPECT(shown && got, "no make demo table in %s", shown ? "make demo's output" : "README.md");
    if (shown && got) compare_lines(shown, got, line_of(readme, strstr(readme, "| run   ")), "make demo");
    free(readme);
    free(printed);
    free(shown);
    free(got);
}

/* ---- 5. the reader's path and the data flow ---------------------------- */

/* Whether text defines function name: a line that starts at column 0
** (a return type), names "name(", and is not a declaration (no ';' before
** the line's end). */
static int defines(const char *text, const char *name)
{
    const size_t n = strlen(name);
    const char *p;
    for (p = text; (p = strstr(p, name)) != NULL; p += n) {
        const char *line = p, *eol = strchr(p, '\n');
        while (line > text && line[-1] != '\n') line--;
        if (p[n] != '(' || (p > text && is_word_char(p[-1])) || !isalpha((unsigned char)line[0])) continue;
        if (!memchr(line, ';', (size_t)((eol ? eol : p + strlen(p)) - line))) return 1;
    }
    return 0;
}

/* The README's "A reader's path: ten functions": ten rows | # | `name` |
** `file` | ... |, numbered 1..10, each function defined in the file the
** row names. */
static void test_readers_path(void)
{
    char *readme = (char *)tu_slurp("README.md", NULL);
    const char *p = readme ? strstr(readme, "## A reader's path: ten functions") : NULL;
    int rows = 0;
    EXPECT(p != NULL, "README.md: no section \"A reader's path: ten functions\"");
    while (p && (p = strstr(p, "\n| ")) != NULL) {
        char name[80], file[40];
        int number;
        char *source;
        p++;
        if (sscanf(p, "| %d | `%79[a-z0-9_]` | `%39[a-z.]` |", &number, name, file) != 3) {
            if (rows > 0) break;           /* the table's end */
            continue;                      /* its header */
        }
        rows++;
        EXPECT(number == rows, "README.md:%d: the reader's path numbers row %d as %d", line_of(readme, p), rows,
               number);
        source = (char *)tu_slurp(file, NULL);
        EXPECT(source && defines(source, name), "README.md:%d: the reader's path names %s in %s, which does not "
               "define it", line_of(readme, p), name, file);
        free(source);
    }
    EXPECT(rows == 10, "README.md: the reader's path has %d functions, not ten", rows);
    free(readme);
}

/* Whether a line draws a flow: two arrows or more ("->", "-->" and the
** box-drawing arrow; not C's p->field, whose arrow has a word either side). */
static int draws_flow(const char *line, size_t n)
{
    int arrows = 0;
    size_t i;
    for (i = 0; i + 1 < n; i++) {
        if (strncmp(line + i, "\xe2\x94\x80\xe2\x96\xba", 6) == 0 && i + 6 <= n) arrows++, i += 5;
        else if (line[i] == '-' && line[i + 1] == '>' &&
                 !(i > 0 && is_word_char(line[i - 1]) && i + 2 < n && is_word_char(line[i + 2])))
            arrows++, i++;
    }
    return arrows >= 2;
}

/* The lines of path (README.md, or a C file's comments) that draw a flow,
** outside README.md's "The data flow" section: each one an EXPECT
** failure.  Returns how many lines inside it do. */
static int check_drawings(const char *path)
{
    char *text = (char *)tu_slurp(path, NULL), *p = text, *notes = NULL;
    const char *flow = text && strcmp(path, "README.md") == 0 ? strstr(text, "## The data flow\n") : NULL;
    const char *flow_end = flow ? strstr(flow + 1, "\n## ") : NULL;
    int inside = 0;
    if (text && !flow) {                   /* a C file: its comments alone */
        notes = malloc(strlen(text) + 1);
        if (notes) split_c(text, notes);
        free(text);
        p = text = notes;
    }
    while (p && *p) {
        const char *eol = strchr(p, '\n');
        size_t n = eol ? (size_t)(eol - p) : strlen(p);
        if (draws_flow(p, n)) {
            int in_flow = flow && p > flow && (!flow_end || p < flow_end);
            inside += in_flow;
            EXPECT(in_flow, "%s:%d: a drawing of the data flow outside README.md's \"The data flow\": %.*s", path,
                   line_of(text, p), (int)n, p);
        }
        p += n + (eol != NULL);
    }
    free(text);
    return inside;
}

static void count_drawing(const char *path, void *user)
{
    *(int *)user += check_drawings(path);
}

/* The data flow is drawn once: in README.md's section of that name, and
** in no comment of the core or of examples/. */
static void test_data_flow_drawn_once(void)
{
    int inside = check_drawings("README.md");
    EXPECT(inside >= 3, "README.md: \"The data flow\" draws %d lines of flow", inside);
    inside = 0;
    each_source(".", 0, count_drawing, &inside);
    each_source("examples", 1, count_drawing, &inside);
    EXPECT(inside == 0, "a source file claims README.md's drawing");
}

/* The README holds the contract and the current figures in under 600
** lines (the product's rule: no history). */
static void test_readme_short(void)
{
    char *readme = (char *)tu_slurp("README.md", NULL), *p;
    int lines = 0;
    CHECK(readme != NULL, "README.md unreadable");
    for (p = readme; *p; p++) lines += *p == '\n';
    EXPECT(lines < 600, "README.md has %d lines, not under 600", lines);
    free(readme);
}

void suite_drift(void)
{
    test_run("drift: every identifier a comment or the README names exists", test_identifiers_exist);
    test_run("drift: every option of a README command line is in its program's --help", test_options_exist);
    test_run("drift: the README's example outputs are what the commands print", test_example_outputs);
    test_run("drift: the README's ten functions are defined where it says", test_readers_path);
    test_run("drift: the data flow is drawn once, in the README", test_data_flow_drawn_once);
    test_run("drift: the README is under 600 lines", test_readme_short);
    test_run("drift long: make demo prints the README's table (make test-long)", test_demo_output);
}
