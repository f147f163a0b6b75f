/* The bus's per-message hot path in C: tags, sealing, opening, decoding and replay checks.
 *
 * Every piece has a pure-Python twin, which stays the reference and the fallback where no
 * compiler was at hand: Mac in protocol/auth.py (hashlib), seal and open in protocol/codec.py,
 * decode in protocol/schema.py, ReplayGuard in protocol/replay.py, Receiver in rascal/runtime/bus.py
 * (Bus._accept). The C side only takes the common case: a well-formed, authentic message whose
 * body has exactly the layout this build declares. For anything else it returns None and the
 * caller runs the Python twin, which accepts the other layout versions or raises the precise
 * ProtocolError. So C accepts a subset of what Python accepts, builds the same values, and words
 * no error but two: the replay guard's, and bad_mac for a tag it has checked and found wrong, so
 * that no datagram's tag is computed twice (a forger must not buy two or three MACs with one).
 *
 * Fragment datagrams (flags bit 0x02) never take this path: locate() refuses them and the Bus
 * sends them to the Python reassembler (protocol/framing.py), which checks each fragment's own
 * tag. Fragments are rare (large messages only), so they need no C twin. Nor do messages with an
 * Ed25519 signature (flags bit 0x04, the low-rate command channels): locate() refuses any flag
 * but SIGNED, and the Receiver leaves every message of a governed route to Python, which checks
 * command authority (protocol/authority.py).
 *
 * Layout (little-endian, SPEC.md is normative):
 *   magic "RB" | version u8 | flags u8 | type_id u16 | source_id u16 | key_id u16 |
 *   channel_len u8 | reserved u8 | seq u64 | t_meas_ns i64 | t_pub_ns i64 |
 *   channel | msgpack body | [Ed25519 signature, 64 B: never here] | tag (16 B, if signed)
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* Bumped whenever a signature or a plan's meaning changes: Python ignores a stale build. */
#define FASTPATH_ABI 6

#define PREFIX_BYTES 12
#define HEADER_BYTES 36
#define TAG_BYTES 16
#define MAX_CHANNEL_BYTES 64
#define VERSION 1
#define FLAG_SIGNED 0x01


static inline uint16_t get_u16(const unsigned char *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

static inline uint64_t get_u64(const unsigned char *p) {
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    uint64_t value;
    memcpy(&value, p, 8); /* one load where the host is little-endian, as the wire is */
    return value;
#else
    uint64_t value = 0;
    for (int i = 7; i >= 0; i--) value = (value << 8) | p[i];
    return value;
#endif
}

static inline void put_u64(unsigned char *p, uint64_t value) {
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    memcpy(p, &value, 8);
#else
    for (int i = 0; i < 8; i++, value >>= 8) p[i] = (unsigned char)value;
#endif
}

/* -- keyed BLAKE2b-128 (RFC 7693) ---------------------------------------------------------------
 * The MAC of every message, once to send it and once to receive it. It is hashlib's
 * blake2b(key=key, digest_size=16), tag for tag (the tests hold it to that), without hashlib's
 * three method calls and two objects per tag: a Mac keeps the state after its key block. */

static const uint64_t BLAKE2B_IV[8] = {
    0x6a09e667f3bcc908ULL, 0xbb67ae8584caa73bULL, 0x3c6ef372fe94f82bULL, 0xa54ff53a5f1d36f1ULL,
    0x510e527fade682d1ULL, 0x9b05688c2b3e6c1fULL, 0x1f83d9abfb41bd6bULL, 0x5be0cd19137e2179ULL,
};

static const uint8_t BLAKE2B_SIGMA[10][16] = {
    {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15}, {14, 10, 4, 8, 9, 15, 13, 6, 1, 12, 0, 2, 11, 7, 5, 3},
    {11, 8, 12, 0, 5, 2, 15, 13, 10, 14, 3, 6, 7, 1, 9, 4}, {7, 9, 3, 1, 13, 12, 11, 14, 2, 6, 5, 10, 4, 0, 15, 8},
    {9, 0, 5, 7, 2, 4, 10, 15, 14, 1, 11, 12, 6, 8, 3, 13}, {2, 12, 6, 10, 0, 11, 8, 3, 4, 13, 7, 5, 15, 14, 1, 9},
    {12, 5, 1, 15, 14, 13, 4, 10, 0, 7, 6, 3, 9, 2, 8, 11}, {13, 11, 7, 14, 12, 1, 3, 9, 5, 0, 15, 4, 8, 6, 2, 10},
    {6, 15, 14, 9, 11, 3, 0, 8, 12, 2, 13, 7, 1, 4, 10, 5}, {10, 2, 8, 4, 7, 6, 1, 5, 15, 11, 9, 14, 3, 12, 13, 0},
};

#define BLOCK_BYTES 128
#define KEY_MAX_BYTES 64

static inline uint64_t rotr64(uint64_t x, int n) { return (x >> n) | (x << (64 - n)); }

#define G(a, b, c, d, x, y)            \
    do {                               \
        v[a] = v[a] + v[b] + (x);      \
        v[d] = rotr64(v[d] ^ v[a], 32); \
        v[c] = v[c] + v[d];            \
        v[b] = rotr64(v[b] ^ v[c], 24); \
        v[a] = v[a] + v[b] + (y);      \
        v[d] = rotr64(v[d] ^ v[a], 16); \
        v[c] = v[c] + v[d];            \
        v[b] = rotr64(v[b] ^ v[c], 63); \
    } while (0)

#define ROUND(r)                                                                     \
    do {                                                                             \
        G(0, 4, 8, 12, m[BLAKE2B_SIGMA[r][0]], m[BLAKE2B_SIGMA[r][1]]);              \
        G(1, 5, 9, 13, m[BLAKE2B_SIGMA[r][2]], m[BLAKE2B_SIGMA[r][3]]);              \
        G(2, 6, 10, 14, m[BLAKE2B_SIGMA[r][4]], m[BLAKE2B_SIGMA[r][5]]);             \
        G(3, 7, 11, 15, m[BLAKE2B_SIGMA[r][6]], m[BLAKE2B_SIGMA[r][7]]);             \
        G(0, 5, 10, 15, m[BLAKE2B_SIGMA[r][8]], m[BLAKE2B_SIGMA[r][9]]);             \
        G(1, 6, 11, 12, m[BLAKE2B_SIGMA[r][10]], m[BLAKE2B_SIGMA[r][11]]);           \
        G(2, 7, 8, 13, m[BLAKE2B_SIGMA[r][12]], m[BLAKE2B_SIGMA[r][13]]);            \
        G(3, 4, 9, 14, m[BLAKE2B_SIGMA[r][14]], m[BLAKE2B_SIGMA[r][15]]);            \
    } while (0)

/* One block into the chained state h; `bytes_so_far` counts this block's bytes too. */
static void blake2b_compress(uint64_t h[8], const unsigned char block[BLOCK_BYTES], uint64_t bytes_so_far, int last) {
    uint64_t m[16], v[16];
    for (int i = 0; i < 16; i++) m[i] = get_u64(block + 8 * i);
    for (int i = 0; i < 8; i++) {
        v[i] = h[i];
        v[i + 8] = BLAKE2B_IV[i];
    }
    v[12] ^= bytes_so_far; /* the counter's high word stays 0: messages are far below 2^64 B */
    if (last) v[14] = ~v[14];
    /* Rounds spelled out, so the message schedule is constant and v lives in registers. */
    ROUND(0); ROUND(1); ROUND(2); ROUND(3); ROUND(4); ROUND(5);
    ROUND(6); ROUND(7); ROUND(8); ROUND(9); ROUND(0); ROUND(1);
    for (int i = 0; i < 8; i++) h[i] ^= v[i] ^ v[i + 8];
}

/* Key material must not outlive its use in freed heap or dead stack memory, and a plain memset
 * just before free() or a return is a dead store the compiler may drop. */
static void wipe(void *p, size_t n) {
#if defined(__GLIBC__) && (__GLIBC__ > 2 || (__GLIBC__ == 2 && __GLIBC_MINOR__ >= 25))
    explicit_bzero(p, n);
#else
    volatile unsigned char *v = p;
    while (n--) *v++ = 0;
#endif
}

#if defined(__GNUC__)
#define NOINLINE __attribute__((noinline))
#else
#define NOINLINE
#endif

/* Overwrites the stack that a noinline call made from the same frame just used: blake2b_compress
 * copies the key block into its locals (m, v, register spills), which no wipe() can name. */
static NOINLINE void burn_stack(void) {
    unsigned char frame[2048];
    wipe(frame, sizeof frame);
}

/* Keeps no key, only what it derives: the tag of empty data is the one tag that compresses the
 * key block as the last block, so it is made once at keying. */
typedef struct {
    PyObject_HEAD
    uint64_t keyed[8];  /* parameter block applied and the key block compressed */
    unsigned char empty_tag[TAG_BYTES];
} MacObject;

static PyTypeObject MacType;

/* noinline: its frame holds the key block, so mac_init can burn it once this returns. */
static NOINLINE void mac_set_key(MacObject *self, const void *key, Py_ssize_t len) {
    unsigned char key_block[BLOCK_BYTES];
    uint64_t h[8];
    memset(key_block, 0, BLOCK_BYTES);
    memcpy(key_block, key, len);
    for (int i = 0; i < 8; i++) h[i] = BLAKE2B_IV[i];
    h[0] ^= 0x01010000ULL ^ ((uint64_t)len << 8) ^ TAG_BYTES; /* fanout 1, depth 1 */
    memcpy(self->keyed, h, sizeof h);
    blake2b_compress(self->keyed, key_block, BLOCK_BYTES, 0);
    blake2b_compress(h, key_block, BLOCK_BYTES, 1); /* empty data: the key block is the last block */
    for (int i = 0; i < TAG_BYTES / 8; i++) put_u64(self->empty_tag + 8 * i, h[i]);
    wipe(key_block, sizeof key_block);
}

static int mac_init(MacObject *self, PyObject *args, PyObject *kwargs) {
    static char *keywords[] = {"key", NULL};
    Py_buffer key;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "y*:Mac", keywords, &key)) return -1;
    if (key.len < 1 || key.len > KEY_MAX_BYTES) {
        PyBuffer_Release(&key);
        PyErr_SetString(PyExc_ValueError, "a BLAKE2b key is 1 to 64 bytes");
        return -1;
    }
    mac_set_key(self, key.buf, key.len);
    burn_stack();
    PyBuffer_Release(&key);
    return 0;
}

static void mac_dealloc(MacObject *self) {
    wipe(self->keyed, sizeof self->keyed); /* the keyed state forges tags as well as the key does */
    wipe(self->empty_tag, sizeof self->empty_tag);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static void mac_tag(const MacObject *mac, const unsigned char *data, Py_ssize_t len, unsigned char *tag) {
    uint64_t h[8];
    unsigned char last[BLOCK_BYTES];
    if (len == 0) {
        memcpy(tag, mac->empty_tag, TAG_BYTES);
        return;
    }
    memcpy(h, mac->keyed, sizeof h);
    uint64_t done = BLOCK_BYTES;
    for (; len > BLOCK_BYTES; data += BLOCK_BYTES, len -= BLOCK_BYTES) {
        done += BLOCK_BYTES;
        blake2b_compress(h, data, done, 0);
    }
    memset(last, 0, BLOCK_BYTES);
    memcpy(last, data, len);
    blake2b_compress(h, last, done + (uint64_t)len, 1);
    for (int i = 0; i < TAG_BYTES / 8; i++) put_u64(tag + 8 * i, h[i]);
}

/* Mac.digest(data) -> the 16-byte tag, as hashlib.blake2b(data, key=key, digest_size=16) */
static PyObject *mac_digest(MacObject *self, PyObject *arg) {
    Py_buffer data;
    if (PyObject_GetBuffer(arg, &data, PyBUF_SIMPLE) < 0) return NULL;
    unsigned char tag[TAG_BYTES];
    mac_tag(self, data.buf, data.len, tag);
    PyBuffer_Release(&data);
    return PyBytes_FromStringAndSize((const char *)tag, TAG_BYTES);
}

static PyMethodDef mac_methods[] = {
    {"digest", (PyCFunction)mac_digest, METH_O, "digest(data) -> 16-byte keyed BLAKE2b tag"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject MacType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "protocol._fastpath.Mac",
    .tp_basicsize = sizeof(MacObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "Mac(key): keyed BLAKE2b-128, the bus's message tag",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)mac_init,
    .tp_dealloc = (destructor)mac_dealloc,
    .tp_methods = mac_methods,
};

/* The tag of buf[0:len] with `mac`, which must be a Mac: 0, or -1 with TypeError. */
static int compute_tag(PyObject *mac, const char *buf, Py_ssize_t len, unsigned char *tag) {
    if (!Py_IS_TYPE(mac, &MacType)) {
        PyErr_SetString(PyExc_TypeError, "messages are signed and verified with protocol._fastpath.Mac objects");
        return -1;
    }
    mac_tag((MacObject *)mac, (const unsigned char *)buf, len, tag);
    return 0;
}

/* seal(prefix, seq, t_meas_ns, t_pub_ns, channel, body, mac) -> bytes
 * One message from its parts; signed with the Mac, or unsigned when mac is None. */
static PyObject *seal(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError, "seal() takes 7 arguments");
        return NULL;
    }
    PyObject *prefix = args[0], *channel = args[4], *body = args[5], *mac = args[6];
    if (!PyBytes_Check(prefix) || PyBytes_GET_SIZE(prefix) != PREFIX_BYTES || !PyBytes_Check(channel) ||
        !PyBytes_Check(body)) {
        PyErr_SetString(PyExc_TypeError, "seal() needs a 12-byte prefix, channel bytes and body bytes");
        return NULL;
    }
    unsigned long long seq = PyLong_AsUnsignedLongLong(args[1]);
    if (seq == (unsigned long long)-1 && PyErr_Occurred()) return NULL;
    long long t_meas = PyLong_AsLongLong(args[2]);
    if (t_meas == -1 && PyErr_Occurred()) return NULL;
    long long t_pub = PyLong_AsLongLong(args[3]);
    if (t_pub == -1 && PyErr_Occurred()) return NULL;
    int signed_ = mac != Py_None;
    Py_ssize_t channel_len = PyBytes_GET_SIZE(channel), body_len = PyBytes_GET_SIZE(body);
    Py_ssize_t unsealed = HEADER_BYTES + channel_len + body_len;
    PyObject *out = PyBytes_FromStringAndSize(NULL, unsealed + (signed_ ? TAG_BYTES : 0));
    if (out == NULL) return NULL;
    unsigned char *p = (unsigned char *)PyBytes_AS_STRING(out);
    memcpy(p, PyBytes_AS_STRING(prefix), PREFIX_BYTES);
    put_u64(p + 12, (uint64_t)seq);
    put_u64(p + 20, (uint64_t)t_meas);
    put_u64(p + 28, (uint64_t)t_pub);
    memcpy(p + HEADER_BYTES, PyBytes_AS_STRING(channel), channel_len);
    memcpy(p + HEADER_BYTES + channel_len, PyBytes_AS_STRING(body), body_len);
    if (signed_ && compute_tag(mac, (const char *)p, unsealed, p + unsealed) < 0) {
        Py_DECREF(out);
        return NULL;
    }
    return out;
}

static PyObject *ProtocolError, *reason_replay, *reason_stale, *reason_future, *reason_bad_mac;

/* Raises ProtocolError(reason, detail, source_id); steals detail (NULL: an error is set). */
static void reject(PyObject *reason, long source_id, PyObject *detail) {
    if (detail == NULL) return;
    PyObject *error = PyObject_CallFunction(ProtocolError, "OOl", reason, detail, source_id);
    Py_DECREF(detail);
    if (error != NULL) {
        PyErr_SetObject((PyObject *)Py_TYPE(error), error);
        Py_DECREF(error);
    }
}

/* A message that passed every check open() makes, located in its datagram. */
typedef struct {
    const unsigned char *p;
    Py_ssize_t size, body_start, body_end;
    unsigned channel_len;
} Located;

/* The checks of Codec.open: 1 authentic and well-formed, 0 not (Python words why), -1 error,
 * which is ProtocolError(bad_mac) for a wrong tag: Python, given the same datagram, would pass
 * every check made before the tag and then refuse it as bad_mac, so it is refused here, once. */
static int locate(PyObject *data, PyObject *macs_by_id, Py_ssize_t max_bytes, Located *m) {
    if (!PyBytes_CheckExact(data)) return 0;
    Py_ssize_t size = PyBytes_GET_SIZE(data);
    const unsigned char *p = (const unsigned char *)PyBytes_AS_STRING(data);
    if (size < HEADER_BYTES || size > max_bytes || p[0] != 'R' || p[1] != 'B' || p[2] != VERSION) return 0;
    unsigned flags = p[3], channel_len = p[10];
    if ((flags & ~FLAG_SIGNED) || channel_len == 0 || channel_len > MAX_CHANNEL_BYTES) return 0;
    Py_ssize_t body_start = HEADER_BYTES + channel_len, body_end = size;
    if (flags & FLAG_SIGNED) {
        /* Signed messages in the unsigned mode are accepted unverified: Python's path does that. */
        body_end = size - TAG_BYTES;
        if (body_end <= body_start || macs_by_id == Py_None) return 0;
        PyObject *key_id = PyLong_FromLong(get_u16(p + 8));
        if (key_id == NULL) return -1;
        PyObject *mac = PyDict_GetItemWithError(macs_by_id, key_id);
        Py_DECREF(key_id);
        if (mac == NULL) return PyErr_Occurred() ? -1 : 0;
        unsigned char tag[TAG_BYTES];
        if (compute_tag(mac, (const char *)p, body_end, tag) < 0) return -1;
        unsigned char diff = 0; /* constant time, as hmac.compare_digest */
        for (int i = 0; i < TAG_BYTES; i++) diff |= tag[i] ^ p[body_end + i];
        if (diff) {
            reject(reason_bad_mac, get_u16(p + 6), PyUnicode_FromString(""));
            return -1;
        }
    } else if (macs_by_id != Py_None || body_start >= body_end) {
        return 0;
    }
    for (Py_ssize_t i = HEADER_BYTES; i < body_start; i++) {
        if (p[i] >= 0x80) return 0;
    }
    *m = (Located){p, size, body_start, body_end, channel_len};
    return 1;
}

static PyObject *channel_of(const Located *m) {
    return PyUnicode_DecodeASCII((const char *)m->p + HEADER_BYTES, m->channel_len, NULL);
}

/* A tuple subclass instance (NamedTuple) from n new references; steals them, NULLs included. */
static PyObject *new_record(PyTypeObject *cls, PyObject **items, Py_ssize_t n) {
    PyObject *record = cls->tp_alloc(cls, n);
    int failed = record == NULL;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (items[i] == NULL) failed = 1;
        if (record != NULL) {
            PyTuple_SET_ITEM(record, i, items[i]); /* NULL items are fine for the dealloc below */
        } else {
            Py_XDECREF(items[i]);
        }
    }
    if (failed) {
        Py_XDECREF(record);
        return NULL;
    }
    return record;
}

static int check_keys_arg(PyObject *macs_by_id) {
    if (macs_by_id != Py_None && !PyDict_Check(macs_by_id)) {
        PyErr_SetString(PyExc_TypeError, "macs_by_id must be a dict of Mac objects by key id, or None");
        return -1;
    }
    return 0;
}

/* open(data, opened_cls, macs_by_id, max_message_bytes) -> Opened | None
 * macs_by_id: dict of key id -> Mac, or None for the explicit unsigned mode. Raises
 * ProtocolError(bad_mac) for a wrong tag. */
static PyObject *open_message(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "open() takes 4 arguments");
        return NULL;
    }
    PyObject *data = args[0];
    if (!PyType_Check(args[1]) || check_keys_arg(args[2]) < 0) {
        PyErr_SetString(PyExc_TypeError, "open() needs the Opened class and a dict of Macs or None");
        return NULL;
    }
    Py_ssize_t max_bytes = PyLong_AsSsize_t(args[3]);
    if (max_bytes == -1 && PyErr_Occurred()) return NULL;
    Located m;
    int status = locate(data, args[2], max_bytes, &m);
    if (status < 0) return NULL;
    if (status == 0) Py_RETURN_NONE;
    PyObject *body = NULL, *whole = PyMemoryView_FromObject(data);
    if (whole != NULL) {
        body = PySequence_GetSlice(whole, m.body_start, m.body_end);
        Py_DECREF(whole);
    }
    PyObject *fields[7] = {
        PyLong_FromLong(get_u16(m.p + 4)),
        PyLong_FromLong(get_u16(m.p + 6)),
        PyLong_FromUnsignedLongLong(get_u64(m.p + 12)),
        PyLong_FromLongLong((long long)get_u64(m.p + 20)),
        PyLong_FromLongLong((long long)get_u64(m.p + 28)),
        channel_of(&m),
        body,
    };
    return new_record((PyTypeObject *)args[1], fields, 7);
}

/* -- typed decode ------------------------------------------------------------------------------
 * A plan is (cls, kinds, subplans): kinds is bytes with one code per field, subplans a tuple with
 * the plan of each 'R' field's record type (None elsewhere). Codes:
 *   f float (an int passes too; floats must be finite)  i int  b bool  s str  y bytes
 *   F tuple of finite floats/ints   I B S Y tuple of int / bool / str / bytes   R tuple of records
 * A decoded value is 1, "take the Python decoder" 0, an error -1. */

static int is_number(PyObject *value) {
    if (PyFloat_Check(value)) return isfinite(PyFloat_AS_DOUBLE(value));
    return PyLong_Check(value);
}

static int scalar_ok(char kind, PyObject *value) {
    switch (kind) {
        case 'f': return is_number(value);
        case 'i': return PyLong_Check(value);
        case 'b': return PyBool_Check(value);
        case 's': return PyUnicode_Check(value);
        case 'y': return PyBytes_Check(value);
        default: return 0;
    }
}

static int decode_into(PyObject *plan, PyObject *raw, PyObject **out);

static int sequence_ok(char kind, PyObject *raw) {
    char item_kind = kind == 'F' ? 'f' : (char)(kind - 'A' + 'a');  /* I -> i, B -> b, ... */
    Py_ssize_t n = PyTuple_GET_SIZE(raw);
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!scalar_ok(item_kind, PyTuple_GET_ITEM(raw, i))) return 0;
    }
    return 1;
}

static int decode_records(PyObject *plan, PyObject *raw, PyObject **out) {
    Py_ssize_t n = PyTuple_GET_SIZE(raw);
    PyObject *records = PyTuple_New(n);
    if (records == NULL) return -1;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *record;
        int status = decode_into(plan, PyTuple_GET_ITEM(raw, i), &record);
        if (status <= 0) {
            Py_DECREF(records);
            return status;
        }
        PyTuple_SET_ITEM(records, i, record);
    }
    *out = records;
    return 1;
}

/* A plan's parts, checked: its field count, or -1 with TypeError. */
static Py_ssize_t unpack_plan(PyObject *plan, PyTypeObject **cls, const char **kind, PyObject **subplans) {
    if (!PyTuple_CheckExact(plan) || PyTuple_GET_SIZE(plan) != 3) {
        PyErr_SetString(PyExc_TypeError, "a plan is (cls, kinds, subplans)");
        return -1;
    }
    PyObject *cls_object = PyTuple_GET_ITEM(plan, 0), *kinds = PyTuple_GET_ITEM(plan, 1);
    *subplans = PyTuple_GET_ITEM(plan, 2);
    if (!PyType_Check(cls_object) || !PyType_IsSubtype((PyTypeObject *)cls_object, &PyTuple_Type) ||
        !PyBytes_Check(kinds) || !PyTuple_Check(*subplans) || PyTuple_GET_SIZE(*subplans) != PyBytes_GET_SIZE(kinds)) {
        PyErr_SetString(PyExc_TypeError, "a plan is (cls, kinds, subplans)");
        return -1;
    }
    *cls = (PyTypeObject *)cls_object;
    *kind = PyBytes_AS_STRING(kinds);
    return PyBytes_GET_SIZE(kinds);
}

static int decode_into(PyObject *plan, PyObject *raw, PyObject **out) {
    PyTypeObject *cls;
    const char *kind;
    PyObject *subplans;
    Py_ssize_t n = unpack_plan(plan, &cls, &kind, &subplans);
    if (n < 0) return -1;
    if (!PyTuple_CheckExact(raw) || PyTuple_GET_SIZE(raw) != n) return 0;
    PyObject *msg = cls->tp_alloc(cls, n); /* zeroed: items not yet set are NULL */
    if (msg == NULL) return -1;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *value = PyTuple_GET_ITEM(raw, i), *converted = NULL;
        int status;
        if (kind[i] >= 'a') {
            status = scalar_ok(kind[i], value);
        } else if (!PyTuple_CheckExact(value)) {
            status = 0;
        } else if (kind[i] == 'R') {
            status = decode_records(PyTuple_GET_ITEM(subplans, i), value, &converted);
        } else {
            status = sequence_ok(kind[i], value);
        }
        if (status <= 0) {
            Py_DECREF(msg);  /* items not yet set are NULL, which tuple dealloc skips */
            return status;
        }
        if (converted == NULL) {
            Py_INCREF(value);
            converted = value;
        }
        PyTuple_SET_ITEM(msg, i, converted);
    }
    *out = msg;
    return 1;
}

/* decode(plan, raw) -> message | None */
static PyObject *decode(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "decode() takes 2 arguments");
        return NULL;
    }
    PyObject *msg;
    int status = decode_into(args[0], args[1], &msg);
    if (status < 0) return NULL;
    if (status == 0) Py_RETURN_NONE;
    return msg;
}

/* -- reading a body straight into its type --------------------------------------------------------
 * msgpack.unpackb(body, use_list=False) followed by decode(plan, raw), in one pass: the plan says
 * what each field must be, so values go straight into the message and no intermediate tuples are
 * made. Anything the plan does not expect (nil, maps, ext types, other lengths, bad UTF-8, bytes
 * left over) gives 0, and Python's path reads the body instead. Same result where it gives one:
 * msgpack makes ints of every int format, floats of float32/float64, True/False of bools, str
 * of str (UTF-8), bytes of bin; Python's decoder then accepts bools where it wants ints or floats. */

typedef struct {
    const unsigned char *p, *end;
} Reader;

static int need(Reader *r, Py_ssize_t n) { return r->end - r->p >= n; }

static uint64_t get_be(const unsigned char *p, int n) {
    uint64_t value = 0;
    for (int i = 0; i < n; i++) value = (value << 8) | p[i];
    return value;
}

/* Length of the array that starts here, or -1 when there is none. */
static Py_ssize_t read_array_header(Reader *r) {
    if (!need(r, 1)) return -1;
    unsigned char c = *r->p;
    int size = (c & 0xf0) == 0x90 ? 0 : c == 0xdc ? 2 : c == 0xdd ? 4 : -1;
    if (size < 0 || !need(r, 1 + size)) return -1;
    Py_ssize_t n = size == 0 ? (c & 0x0f) : (Py_ssize_t)get_be(r->p + 1, size);
    r->p += 1 + size;
    return n;
}

/* One scalar of the plan's kind as a new reference; NULL without an exception: not that kind. */
static PyObject *read_scalar(Reader *r, char kind) {
    if (!need(r, 1)) return NULL;
    unsigned char c = *r->p;
    if (c == 0xc2 || c == 0xc3) { /* bool: wanted as bool, and passes as int or float */
        if (kind != 'b' && kind != 'i' && kind != 'f') return NULL;
        r->p++;
        return Py_NewRef(c == 0xc3 ? Py_True : Py_False);
    }
    if (kind == 'i' || kind == 'f') {
        if (c <= 0x7f || c >= 0xe0) { /* fixints */
            r->p++;
            return PyLong_FromLong(c <= 0x7f ? c : (long)(int8_t)c);
        }
        if (c >= 0xcc && c <= 0xd3) { /* uint8..64, int8..64 */
            int size = 1 << ((c - 0xcc) & 3);
            if (!need(r, 1 + size)) return NULL;
            uint64_t raw = get_be(r->p + 1, size);
            r->p += 1 + size;
            if (c <= 0xcf) return PyLong_FromUnsignedLongLong(raw);
            int shift = 64 - 8 * size; /* sign-extend */
            return PyLong_FromLongLong((long long)((int64_t)(raw << shift) >> shift));
        }
        if (kind == 'f' && (c == 0xca || c == 0xcb)) {
            int size = c == 0xca ? 4 : 8;
            if (!need(r, 1 + size)) return NULL;
            uint64_t raw = get_be(r->p + 1, size);
            double value;
            if (size == 4) {
                uint32_t bits = (uint32_t)raw;
                float single;
                memcpy(&single, &bits, 4);
                value = single;
            } else {
                memcpy(&value, &raw, 8);
            }
            if (!isfinite(value)) return NULL; /* Python's decoder refuses it, and says why */
            r->p += 1 + size;
            return PyFloat_FromDouble(value);
        }
        return NULL;
    }
    if (kind == 's' || kind == 'y') {
        int size;
        Py_ssize_t length;
        if (kind == 's' && (c & 0xe0) == 0xa0) {
            size = 0, length = c & 0x1f;
        } else if (kind == 's' ? c >= 0xd9 && c <= 0xdb : c >= 0xc4 && c <= 0xc6) {
            size = 1 << (c - (kind == 's' ? 0xd9 : 0xc4));
            if (!need(r, 1 + size)) return NULL;
            length = (Py_ssize_t)get_be(r->p + 1, size);
        } else {
            return NULL;
        }
        if (!need(r, 1 + size + length)) return NULL;
        const char *start = (const char *)r->p + 1 + size;
        PyObject *value = kind == 's' ? PyUnicode_DecodeUTF8(start, length, NULL)
                                      : PyBytes_FromStringAndSize(start, length);
        if (value == NULL) {
            if (!PyErr_ExceptionMatches(PyExc_UnicodeDecodeError)) return NULL; /* MemoryError stays */
            PyErr_Clear();
            return NULL;
        }
        r->p += 1 + size + length;
        return value;
    }
    return NULL;
}

static int read_message(Reader *r, PyObject *plan, PyObject **out);

/* A tuple of scalars of one kind, or of records. 1, 0 (not as planned) or -1. */
static int read_sequence(Reader *r, char kind, PyObject *subplan, PyObject **out) {
    Py_ssize_t n = read_array_header(r);
    if (n < 0 || n > r->end - r->p) return 0; /* every item takes a byte at least */
    PyObject *items = PyTuple_New(n);
    if (items == NULL) return -1;
    char item_kind = kind == 'F' ? 'f' : (char)(kind - 'A' + 'a');
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *item = NULL;
        int status;
        if (kind == 'R') {
            status = read_message(r, subplan, &item);
        } else {
            item = read_scalar(r, item_kind);
            status = item != NULL ? 1 : PyErr_Occurred() ? -1 : 0;
        }
        if (status <= 0) {
            Py_DECREF(items);
            return status;
        }
        PyTuple_SET_ITEM(items, i, item);
    }
    *out = items;
    return 1;
}

static int read_message(Reader *r, PyObject *plan, PyObject **out) {
    PyTypeObject *cls;
    const char *kind;
    PyObject *subplans;
    Py_ssize_t n = unpack_plan(plan, &cls, &kind, &subplans);
    if (n < 0) return -1;
    if (read_array_header(r) != n) return 0;
    PyObject *msg = cls->tp_alloc(cls, n); /* zeroed: items not yet set are NULL */
    if (msg == NULL) return -1;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *value = NULL;
        int status;
        if (kind[i] >= 'a') {
            value = read_scalar(r, kind[i]);
            status = value != NULL ? 1 : PyErr_Occurred() ? -1 : 0;
        } else {
            status = read_sequence(r, kind[i], PyTuple_GET_ITEM(subplans, i), &value);
        }
        if (status <= 0) {
            Py_DECREF(msg);
            return status;
        }
        PyTuple_SET_ITEM(msg, i, value);
    }
    *out = msg;
    return 1;
}

/* The whole body as one message of the plan: 1, 0 (Python's path reads it) or -1. */
static int read_body(PyObject *plan, const unsigned char *body, Py_ssize_t length, PyObject **out) {
    Reader r = {body, body + length};
    int status = read_message(&r, plan, out);
    if (status == 1 && r.p != r.end) { /* msgpack's ExtraData */
        Py_CLEAR(*out);
        return 0;
    }
    return status;
}

/* decode_body(plan, body) -> message | None: msgpack.unpackb + decode in one pass */
static PyObject *decode_body(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "decode_body() takes 2 arguments");
        return NULL;
    }
    Py_buffer body;
    if (PyObject_GetBuffer(args[1], &body, PyBUF_SIMPLE) < 0) return NULL;
    PyObject *msg = NULL;
    int status = read_body(args[0], body.buf, body.len, &msg);
    PyBuffer_Release(&body);
    if (status < 0) return NULL;
    if (status == 0) Py_RETURN_NONE;
    return msg;
}

/* -- replay protection -------------------------------------------------------------------------
 * protocol/replay.py's ReplayGuard, same rules, same errors: per (source id, channel) stream the
 * highest sequence accepted and a 64-message bitmap behind it, the latest t_pub_ns accepted and
 * the start of the source's current life (restarts below its old numbers), plus the freshness
 * window. Streams live in a slot array on a least-recently-used list; a dict finds a stream's
 * slot by its key. */

#define WINDOW 64
#define RESTART_JUMP 1000000

typedef struct {
    PyObject *key; /* (source_id, channel); NULL for a free slot */
    uint64_t first, highest, seen;
    int64_t newest, floor; /* latest t_pub_ns accepted; current life's first (INT64_MIN: none) */
    Py_ssize_t older, newer; /* LRU neighbours, -1 at the ends; `newer` links free slots */
} Stream;

typedef struct {
    PyObject_HEAD
    PyObject *limits;
    long long max_age_ns, max_future_ns;
    Py_ssize_t max_streams, capacity, count, oldest, newest, free;
    PyObject *slot_of; /* key -> slot index (int) */
    Stream *streams;
} ReplayGuardObject;

static PyTypeObject ReplayGuardType;

static int limit_of(PyObject *limits, const char *name, long long *out) {
    PyObject *value = PyObject_GetAttrString(limits, name);
    if (value == NULL) return -1;
    *out = PyLong_AsLongLong(value);
    Py_DECREF(value);
    return (*out == -1 && PyErr_Occurred()) ? -1 : 0;
}

static int guard_init(ReplayGuardObject *self, PyObject *args, PyObject *kwargs) {
    static char *keywords[] = {"limits", NULL};
    PyObject *limits;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "O:ReplayGuard", keywords, &limits)) return -1;
    long long max_streams;
    if (limit_of(limits, "max_age_ns", &self->max_age_ns) < 0 || limit_of(limits, "max_future_ns", &self->max_future_ns) < 0 ||
        limit_of(limits, "max_streams", &max_streams) < 0)
        return -1;
    if (max_streams < 1) {
        PyErr_SetString(PyExc_ValueError, "max_streams must be at least 1");
        return -1;
    }
    Py_XSETREF(self->limits, Py_NewRef(limits));
    Py_XSETREF(self->slot_of, PyDict_New());
    if (self->slot_of == NULL) return -1;
    for (Py_ssize_t i = 0; i < self->capacity; i++) Py_CLEAR(self->streams[i].key);
    PyMem_Free(self->streams);
    self->streams = NULL;
    self->max_streams = (Py_ssize_t)max_streams;
    self->capacity = self->count = 0;
    self->oldest = self->newest = self->free = -1;
    return 0;
}

static void guard_dealloc(ReplayGuardObject *self) {
    PyObject_GC_UnTrack(self);
    for (Py_ssize_t i = 0; i < self->capacity; i++) Py_XDECREF(self->streams[i].key);
    PyMem_Free(self->streams);
    Py_XDECREF(self->slot_of);
    Py_XDECREF(self->limits);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int guard_traverse(ReplayGuardObject *self, visitproc visit, void *arg) {
    Py_VISIT(self->limits);
    Py_VISIT(self->slot_of);
    return 0;
}

static void unlink_stream(ReplayGuardObject *self, Py_ssize_t i) {
    Stream *s = &self->streams[i];
    if (s->older >= 0) self->streams[s->older].newer = s->newer; else self->oldest = s->newer;
    if (s->newer >= 0) self->streams[s->newer].older = s->older; else self->newest = s->older;
}

static void link_newest(ReplayGuardObject *self, Py_ssize_t i) {
    Stream *s = &self->streams[i];
    s->older = self->newest;
    s->newer = -1;
    if (self->newest >= 0) self->streams[self->newest].newer = i; else self->oldest = i;
    self->newest = i;
}

/* Drop slot i's stream: off the list, out of the dict, onto the free list. */
static int drop_stream(ReplayGuardObject *self, Py_ssize_t i) {
    Stream *s = &self->streams[i];
    unlink_stream(self, i);
    int status = PyDict_DelItem(self->slot_of, s->key);
    Py_CLEAR(s->key);
    s->newer = self->free;
    self->free = i;
    self->count--;
    return status;
}

static Py_ssize_t new_stream(ReplayGuardObject *self, PyObject *key, uint64_t seq, int64_t t_pub_ns) {
    if (self->count >= self->max_streams && drop_stream(self, self->oldest) < 0) return -1;
    if (self->free < 0) { /* grow: double, up to max_streams */
        Py_ssize_t capacity = self->capacity ? self->capacity * 2 : 16;
        if (capacity > self->max_streams) capacity = self->max_streams;
        Stream *grown = PyMem_Realloc(self->streams, (size_t)capacity * sizeof(Stream));
        if (grown == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        self->streams = grown;
        for (Py_ssize_t i = capacity - 1; i >= self->capacity; i--) {
            grown[i].key = NULL;
            grown[i].newer = self->free;
            self->free = i;
        }
        self->capacity = capacity;
    }
    Py_ssize_t i = self->free;
    PyObject *slot = PyLong_FromSsize_t(i);
    if (slot == NULL) return -1;
    int status = PyDict_SetItem(self->slot_of, key, slot);
    Py_DECREF(slot);
    if (status < 0) return -1;
    Stream *s = &self->streams[i];
    self->free = s->newer;
    *s = (Stream){Py_NewRef(key), seq, seq, 1, t_pub_ns, INT64_MIN, -1, -1};
    link_newest(self, i);
    self->count++;
    return i;
}

static void reject_age(PyObject *reason, long source_id, const char *format, __int128 age_ns) {
    char *seconds = PyOS_double_to_string((double)age_ns / 1e9, 'f', 3, 0, NULL);
    if (seconds == NULL) return;
    reject(reason, source_id, PyUnicode_FromFormat(format, seconds));
    PyMem_Free(seconds);
}

/* ReplayGuard.check's rules. has_now = 0 skips freshness. Sets *lost; -1 with ProtocolError. */
static int guard_check(ReplayGuardObject *self, long source_id, PyObject *key, uint64_t seq, int64_t t_pub_ns,
                       int has_now, int64_t now_ns, long long *lost) {
    if (self->slot_of == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "ReplayGuard was not initialised");
        return -1;
    }
    if (has_now) {
        if ((__int128)t_pub_ns < (__int128)now_ns - self->max_age_ns) {
            reject_age(reason_stale, source_id, "published %s s ago", (__int128)now_ns - t_pub_ns);
            return -1;
        }
        if ((__int128)t_pub_ns > (__int128)now_ns + self->max_future_ns) {
            reject_age(reason_future, source_id, "published %s s ahead", (__int128)t_pub_ns - now_ns);
            return -1;
        }
    }
    PyObject *slot = PyDict_GetItemWithError(self->slot_of, key);
    if (slot == NULL) {
        if (PyErr_Occurred() || new_stream(self, key, seq, t_pub_ns) < 0) return -1;
        *lost = 0;
        return 0;
    }
    Py_ssize_t i = PyLong_AsSsize_t(slot);
    Stream *s = &self->streams[i];
    if (i != self->newest) { /* least recently used goes first when full, never an active stream */
        unlink_stream(self, i);
        link_newest(self, i);
    }
    if (t_pub_ns < s->floor) {
        reject(reason_replay, source_id,
               PyUnicode_FromFormat("seq %llu was published before its source restarted", (unsigned long long)seq));
        return -1;
    }
    if (seq > s->highest) {
        uint64_t ahead = seq - s->highest;
        s->seen = ahead < WINDOW ? (s->seen << ahead) | 1 : 1;
        s->highest = seq;
        if (t_pub_ns > s->newest) s->newest = t_pub_ns;
        /* a jump of a million or more is a restarted publisher, not a million lost messages */
        *lost = ahead <= RESTART_JUMP ? (long long)ahead - 1 : 0;
        return 0;
    }
    uint64_t behind = s->highest - seq;
    if (behind >= WINDOW || s->seen >> behind & 1) {
        if (!has_now || t_pub_ns <= s->newest) {
            reject(reason_replay, source_id,
                   behind >= WINDOW ? PyUnicode_FromFormat("seq %llu is %llu behind", (unsigned long long)seq,
                                                           (unsigned long long)behind)
                                    : PyUnicode_FromFormat("seq %llu already seen", (unsigned long long)seq));
            return -1;
        }
        /* fresh and published after everything accepted here, so none of it: the source restarted
         * below its old numbers (its wall clock stepped back); follow the new life */
        *s = (Stream){s->key, seq, seq, 1, t_pub_ns, t_pub_ns, s->older, s->newer};
        *lost = 0;
        return 0;
    }
    s->seen |= (uint64_t)1 << behind;
    if (t_pub_ns > s->newest) s->newest = t_pub_ns;
    *lost = seq > s->first ? -1 : 0;
    return 0;
}

static int as_u64(PyObject *value, uint64_t *out) {
    *out = PyLong_AsUnsignedLongLong(value);
    return (*out == (uint64_t)-1 && PyErr_Occurred()) ? -1 : 0;
}

static int as_i64(PyObject *value, int64_t *out) {
    *out = PyLong_AsLongLong(value);
    return (*out == -1 && PyErr_Occurred()) ? -1 : 0;
}

/* check(source_id, channel, seq, t_pub_ns, now_ns) -> lost; as protocol.replay.ReplayGuard.check */
static PyObject *guard_check_method(ReplayGuardObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 5) {
        PyErr_SetString(PyExc_TypeError, "check() takes 5 arguments");
        return NULL;
    }
    long source_id = PyLong_AsLong(args[0]);
    uint64_t seq;
    int64_t t_pub_ns, now_ns = 0;
    if ((source_id == -1 && PyErr_Occurred()) || as_u64(args[2], &seq) < 0 || as_i64(args[3], &t_pub_ns) < 0 ||
        (args[4] != Py_None && as_i64(args[4], &now_ns) < 0))
        return NULL;
    PyObject *key = PyTuple_Pack(2, args[0], args[1]);
    if (key == NULL) return NULL;
    long long lost;
    int status = guard_check(self, source_id, key, seq, t_pub_ns, args[4] != Py_None, now_ns, &lost);
    Py_DECREF(key);
    return status < 0 ? NULL : PyLong_FromLongLong(lost);
}

static PyObject *guard_forget(ReplayGuardObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "forget() takes 2 arguments");
        return NULL;
    }
    PyObject *key = PyTuple_Pack(2, args[0], args[1]);
    if (key == NULL) return NULL;
    PyObject *slot = self->slot_of == NULL ? NULL : PyDict_GetItemWithError(self->slot_of, key);
    Py_DECREF(key);
    if (slot == NULL) {
        if (PyErr_Occurred()) return NULL;
        Py_RETURN_NONE;
    }
    if (drop_stream(self, PyLong_AsSsize_t(slot)) < 0) return NULL;
    Py_RETURN_NONE;
}

static Py_ssize_t guard_len(ReplayGuardObject *self) { return self->count; }

static PyMethodDef guard_methods[] = {
    {"check", (PyCFunction)(void (*)(void))guard_check_method, METH_FASTCALL,
     "check(source_id, channel, seq, t_pub_ns, now_ns) -> lost; raises ProtocolError"},
    {"forget", (PyCFunction)(void (*)(void))guard_forget, METH_FASTCALL, "forget(source_id, channel)"},
    {NULL, NULL, 0, NULL},
};

static PyMemberDef guard_members[] = {
    {"limits", T_OBJECT_EX, offsetof(ReplayGuardObject, limits), READONLY, "the ReplayLimits in force"},
    {NULL, 0, 0, 0, NULL},
};

static PySequenceMethods guard_as_sequence = {.sq_length = (lenfunc)guard_len};

static PyTypeObject ReplayGuardType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "protocol._fastpath.ReplayGuard",
    .tp_basicsize = sizeof(ReplayGuardObject),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_BASETYPE | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "ReplayGuard(limits): protocol.replay's replay and freshness rules, in C",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)guard_init,
    .tp_dealloc = (destructor)guard_dealloc,
    .tp_traverse = (traverseproc)guard_traverse,
    .tp_methods = guard_methods,
    .tp_members = guard_members,
    .tp_as_sequence = &guard_as_sequence,
};

/* -- the whole receive path ----------------------------------------------------------------------
 * Receiver(macs_by_id, max_bytes, routes, replay, envelope_cls): one per Bus, holding what
 * the bus's receive path consults. routes maps channel -> route with attributes type_id, plan,
 * replay_exempt and governed (rascal.runtime.bus._Route); replay is a ReplayGuard of this module;
 * envelope_cls has 10 fields, the last (the signature) None for every message accepted here.
 *
 * accept(data, recv_ns, recv_local_ns, check_freshness)
 *   -> (route, msg, envelope, lost)  a message for a subscribed channel, checked, numbered, decoded
 *   -> False                         authentic, but for a channel nobody here subscribed to
 *   -> None                          anything else, and everything on a governed route (its
 *                                    signature is checked in Python): Python's path decides
 * Raises ProtocolError for a wrong tag (bad_mac, as open() does) and for what the replay guard
 * refuses, and asks the guard last, so that a message left to Python has left no trace in the
 * guard that Python's path would trip over. */

typedef struct {
    PyObject_HEAD
    PyObject *macs_by_id, *routes, *replay, *envelope_cls;
    Py_ssize_t max_bytes;
} ReceiverObject;

static PyObject *name_type_id, *name_plan, *name_replay_exempt, *name_governed;

static int receiver_init(ReceiverObject *self, PyObject *args, PyObject *kwargs) {
    static char *keywords[] = {"macs_by_id", "max_bytes", "routes", "replay", "envelope_cls", NULL};
    PyObject *macs_by_id, *routes, *replay, *envelope_cls;
    Py_ssize_t max_bytes;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "OnO!O!O!:Receiver", keywords, &macs_by_id, &max_bytes,
                                     &PyDict_Type, &routes, &ReplayGuardType, &replay, &PyType_Type, &envelope_cls) ||
        check_keys_arg(macs_by_id) < 0)
        return -1;
    Py_XSETREF(self->macs_by_id, Py_NewRef(macs_by_id));
    Py_XSETREF(self->routes, Py_NewRef(routes));
    Py_XSETREF(self->replay, Py_NewRef(replay));
    Py_XSETREF(self->envelope_cls, Py_NewRef(envelope_cls));
    self->max_bytes = max_bytes;
    return 0;
}

static int receiver_traverse(ReceiverObject *self, visitproc visit, void *arg) {
    Py_VISIT(self->macs_by_id);
    Py_VISIT(self->routes);
    Py_VISIT(self->replay);
    Py_VISIT(self->envelope_cls);
    return 0;
}

static int receiver_clear(ReceiverObject *self) {
    Py_CLEAR(self->macs_by_id);
    Py_CLEAR(self->routes);
    Py_CLEAR(self->replay);
    Py_CLEAR(self->envelope_cls);
    return 0;
}

static void receiver_dealloc(ReceiverObject *self) {
    PyObject_GC_UnTrack(self);
    receiver_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static long route_long(PyObject *route, PyObject *name) {
    PyObject *value = PyObject_GetAttr(route, name);
    if (value == NULL) return -1;
    long result = PyLong_AsLong(value);
    Py_DECREF(value);
    return result;
}

/* The body, decoded to the route's type: 1, or 0 for "leave it to Python", -1 error. */
static int decode_for(PyObject *route, const Located *m, PyObject **msg) {
    PyObject *plan = PyObject_GetAttr(route, name_plan);
    if (plan == NULL) return -1;
    int status = read_body(plan, m->p + m->body_start, m->body_end - m->body_start, msg);
    Py_DECREF(plan);
    return status;
}

static PyObject *receiver_accept(ReceiverObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "accept() takes 4 arguments");
        return NULL;
    }
    if (self->routes == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "Receiver was not initialised");
        return NULL;
    }
    int64_t recv_ns;
    if (as_i64(args[1], &recv_ns) < 0) return NULL;
    int check_freshness = PyObject_IsTrue(args[3]);
    if (check_freshness < 0) return NULL;
    Located m;
    int status = locate(args[0], self->macs_by_id, self->max_bytes, &m);
    if (status <= 0) return status < 0 ? NULL : Py_NewRef(Py_None);
    PyObject *channel = channel_of(&m);
    if (channel == NULL) return NULL;
    PyObject *result = NULL, *msg = NULL, *key = NULL, *route = PyDict_GetItemWithError(self->routes, channel);
    if (route == NULL) {
        result = PyErr_Occurred() ? NULL : Py_NewRef(Py_False);
        goto done;
    }
    Py_INCREF(route);
    long governed = route_long(route, name_governed);
    if (governed != 0) { /* -1: an error, or governed: Python checks the signature */
        result = governed == -1 && PyErr_Occurred() ? NULL : Py_NewRef(Py_None);
        goto done;
    }
    long type_id = get_u16(m.p + 4), source_id = get_u16(m.p + 6);
    long expected = route_long(route, name_type_id);
    if (expected == -1 && PyErr_Occurred()) goto done;
    status = expected == type_id ? decode_for(route, &m, &msg) : 0; /* else WRONG_TYPE, by Python */
    if (status <= 0) {
        result = status < 0 ? NULL : Py_NewRef(Py_None);
        goto done;
    }
    long exempt = route_long(route, name_replay_exempt);
    if (exempt == -1 && PyErr_Occurred()) goto done;
    uint64_t seq = get_u64(m.p + 12);
    int64_t t_pub_ns = (int64_t)get_u64(m.p + 28);
    long long lost = 0;
    if (!exempt) { /* the time protocol judges its own messages (rascal.runtime.bus.REPLAY_EXEMPT) */
        PyObject *source = PyLong_FromLong(source_id);
        key = source == NULL ? NULL : PyTuple_Pack(2, source, channel);
        Py_XDECREF(source);
        if (key == NULL) goto done;
        if (guard_check((ReplayGuardObject *)self->replay, source_id, key, seq, t_pub_ns, check_freshness, recv_ns,
                        &lost) < 0)
            goto done;
    }
    PyObject *fields[10] = {
        Py_NewRef(channel),
        PyLong_FromLong(source_id),
        PyLong_FromUnsignedLongLong(seq),
        PyLong_FromLongLong((long long)get_u64(m.p + 20)),
        PyLong_FromLongLong(t_pub_ns),
        Py_NewRef(args[1]),
        PyLong_FromLong(type_id),
        PyLong_FromSsize_t(m.size),
        Py_NewRef(args[2]),
        Py_NewRef(Py_None),
    };
    PyObject *envelope = new_record((PyTypeObject *)self->envelope_cls, fields, 10);
    PyObject *lost_count = envelope == NULL ? NULL : PyLong_FromLongLong(lost);
    if (lost_count != NULL) result = PyTuple_Pack(4, route, msg, envelope, lost_count);
    Py_XDECREF(envelope);
    Py_XDECREF(lost_count);
done:
    Py_XDECREF(key);
    Py_XDECREF(msg);
    Py_XDECREF(route);
    Py_DECREF(channel);
    return result;
}

static PyMethodDef receiver_methods[] = {
    {"accept", (PyCFunction)(void (*)(void))receiver_accept, METH_FASTCALL,
     "accept(data, recv_ns, recv_local_ns, check_freshness) -> (route, msg, envelope, lost) | False | None"},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject ReceiverType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "protocol._fastpath.Receiver",
    .tp_basicsize = sizeof(ReceiverObject),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "Receiver(macs_by_id, max_bytes, routes, replay, envelope_cls): a bus's receive path",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)receiver_init,
    .tp_dealloc = (destructor)receiver_dealloc,
    .tp_traverse = (traverseproc)receiver_traverse,
    .tp_clear = (inquiry)receiver_clear,
    .tp_methods = receiver_methods,
};

static PyMethodDef methods[] = {
    {"seal", (PyCFunction)(void (*)(void))seal, METH_FASTCALL, "seal(prefix, seq, t_meas_ns, t_pub_ns, channel, body, mac)"},
    {"open", (PyCFunction)(void (*)(void))open_message, METH_FASTCALL, "open(data, opened_cls, macs_by_id, max_bytes)"},
    {"decode", (PyCFunction)(void (*)(void))decode, METH_FASTCALL, "decode(plan, raw) -> message | None"},
    {"decode_body", (PyCFunction)(void (*)(void))decode_body, METH_FASTCALL, "decode_body(plan, body) -> message | None"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module_def = {
    .m_base = PyModuleDef_HEAD_INIT, .m_name = "protocol._fastpath", .m_size = -1, .m_methods = methods};

PyMODINIT_FUNC PyInit__fastpath(void) {
    name_type_id = PyUnicode_InternFromString("type_id");
    name_plan = PyUnicode_InternFromString("plan");
    name_replay_exempt = PyUnicode_InternFromString("replay_exempt");
    name_governed = PyUnicode_InternFromString("governed");
    if (!name_type_id || !name_plan || !name_replay_exempt || !name_governed) return NULL;
    PyObject *errors = PyImport_ImportModule("protocol.errors");
    if (errors == NULL) return NULL;
    ProtocolError = PyObject_GetAttrString(errors, "ProtocolError");
    PyObject *reasons = PyObject_GetAttrString(errors, "Reason");
    Py_DECREF(errors);
    if (ProtocolError == NULL || reasons == NULL) return NULL;
    reason_replay = PyObject_GetAttrString(reasons, "REPLAY");
    reason_stale = PyObject_GetAttrString(reasons, "STALE");
    reason_future = PyObject_GetAttrString(reasons, "FUTURE");
    reason_bad_mac = PyObject_GetAttrString(reasons, "BAD_MAC");
    Py_DECREF(reasons);
    if (!reason_replay || !reason_stale || !reason_future || !reason_bad_mac) return NULL;
    if (PyType_Ready(&ReplayGuardType) < 0 || PyType_Ready(&ReceiverType) < 0 || PyType_Ready(&MacType) < 0) return NULL;
    PyObject *module = PyModule_Create(&module_def);
    if (module == NULL) return NULL;
    if (PyModule_AddIntConstant(module, "ABI", FASTPATH_ABI) < 0 ||
        PyModule_AddObjectRef(module, "ReplayGuard", (PyObject *)&ReplayGuardType) < 0 ||
        PyModule_AddObjectRef(module, "Receiver", (PyObject *)&ReceiverType) < 0 ||
        PyModule_AddObjectRef(module, "Mac", (PyObject *)&MacType) < 0) {
        Py_DECREF(module);
        return NULL;
    }
    return module;
}
