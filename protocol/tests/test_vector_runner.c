/* Self-test of the vector runner on hand-made vectors written to a temporary directory: the
 * bytes were built independently of both codecs (Python struct + binascii.crc_hqx + a few lines of
 * COBS), the canonical texts by hand from SPEC section 5. A second directory holds wrong vectors
 * that the runner must count as failures. */
#define _POSIX_C_SOURCE 200809L
#include <unistd.h>

#include "check.h"
#include "vector_runner.h"

static const char *trigger_link_tsv =
    "# hand-made\n"
    "valid\tget_info\t074602010531c000\tmsg_id=1 seq=5\n"
    "valid\tclock\t08460284c840e2010101061f4e0142b600\t"
    "msg_id=132 seq=200 frame_count=123456 ticks=0 top=19999 running=1\n"
    "invalid\tclock_bad_crc\t08460284c840e2010101061f4e0143b600\tBAD_CRC\n"
    "valid\tinfo\t064602810101050201010401010324f407626f7820315c01010101010101010103d51a00\t"
    "msg_id=129 seq=1 protocol_version=1 fw_major=0 fw_minor=2 fw_patch=1 mcu=1 n_outputs=4 "
    "f_cpu=16000000 name=box\\x201\\x5c\n"
    "invalid\tempty\t00\tTRUNCATED\n"
    "invalid\tzero_inside\t0746020005619900\tBAD_COBS\n";

static const char *features_tsv =
    "valid\tone_point\t"
    "4654020164000000030001004d000000e803000000000000ffffffffffffffff000000000000000005000000000000"
    "00060000000000000001000001000000000000c03f000010400000404000008040000040410000f0410000c07f0000"
    "a03ffa0000000000a041cdcccc3d\t"
    "type=1 flags=0 camera_index=3 n_points=1 seq=77 camera_frame=1000 trigger_frame=-1 "
    "device_timestamp_ns=0 edge_recv_ns=5 edge_done_ns=6 total_points=1 part_index=0 part_count=1 "
    "points[0].x_dist=1.5 points[0].y_dist=2.25 points[0].x_undist=3 points[0].y_undist=4 "
    "points[0].area=12 points[0].peak_diff=30 points[0].orientation=nan "
    "points[0].eccentricity=1.25 points[0].cur_val=250 points[0].mean_val=20 "
    "points[0].sumsq_val=0.100000001\n"
    "invalid\tbad_magic\t4655020164000000\tBAD_MAGIC\n"
    "invalid\tshort\t465402\tTRUNCATED\n";

static const char *status_tsv =
    "valid\ttext_escapes\t"
    "465402029000000002000005000400010900000000000000640000000000000002000000000000000000c84200a0"
    "54440080bb440000000063616d20325cc3a900000000000000000000000000000000000000000000000000000000"
    "00000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000"
    "0000000000000000000000000000"
    "\t"
    "type=2 flags=0 camera_index=2 width=1280 height=1024 pixel_format=0 state=1 seq=9 "
    "last_error_code=0 frames_seen=100 frames_dropped=2 fps=100 proc_us_mean=850.5 "
    "proc_us_max=1500 camera_name=cam\\x202\\x5c\\xc3\\xa9 last_error=\n"
    "invalid\tinf_proc_max\t"
    "465402029000000002000005000400010900000000000000640000000000000002000000000000000000c84200a0"
    "54440000807f0000000063616d203200000000000000000000000000000000000000000000000000000000000000"
    "00000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000"
    "0000000000000000000000000000"
    "\tNOT_FINITE\n";

static const char *dvs_words_tsv =
    "valid\tevent_wrap_event\t0b066400000000800e080300\t"
    "n_words=3 words[0].x=5 words[0].y=6 words[0].polarity=1 words[0].ts=100 words[0].reset=0 "
    "words[0].wrap=0 words[0].sync=0 words[0].t_us=100 words[1].x=0 words[1].y=0 "
    "words[1].polarity=0 "
    "words[1].ts=0 words[1].reset=0 words[1].wrap=1 words[1].sync=0 words[2].x=7 words[2].y=8 "
    "words[2].polarity=0 "
    "words[2].ts=3 words[2].reset=0 words[2].wrap=0 words[2].sync=0 words[2].t_us=16387\n"
    "invalid\tpartial_word\t0b0664\tTRUNCATED\n"
    "invalid\treset_and_wrap\t000000c0\tBAD_FIELD\n";

/* Each of these must be counted as a failure. */
static const char *wrong_tsv =
    "valid\twrong_field\t08460284c840e2010101061f4e0142b600\t"
    "msg_id=132 seq=200 frame_count=123456 ticks=0 top=19999 running=0\n"
    "invalid\tnot_an_error\t074602010531c000\tBAD_CRC\n"
    "invalid\twrong_error\t08460284c840e2010101061f4e0143b600\tBAD_COBS\n"
    "valid\tbad_hex\t074602010531c0zz\tmsg_id=1 seq=5\n"
    "valid\tno_delimiter\t074602010531c0\tmsg_id=1 seq=5\n"
    "three\tcolumns\tonly\n";

static int write_file(const char *dir, const char *name, const char *text) {
    char path[512];
    FILE *f;
    snprintf(path, sizeof path, "%s/%s", dir, name);
    f = fopen(path, "wb");
    if (!f)
        return -1;
    fputs(text, f);
    return fclose(f);
}

static void remove_dir(const char *dir, const char *const *names, size_t n) {
    char path[512];
    size_t i;
    for (i = 0; i < n; i++) {
        snprintf(path, sizeof path, "%s/%s", dir, names[i]);
        remove(path);
    }
    rmdir(dir);
}

int main(void) {
    char good[] = "/tmp/ft_vectors_good_XXXXXX", bad[] = "/tmp/ft_vectors_bad_XXXXXX",
         empty[] = "/tmp/ft_vectors_empty_XXXXXX";
    const char *good_names[] = {"trigger_link.tsv", "features.tsv", "status.tsv", "dvs_words.tsv"};
    const char *bad_names[] = {"trigger_link.tsv", "unknown_family.tsv"};
    vr_counts c = {0, 0, NULL};
    c.log = stderr;
    if (!mkdtemp(good) || !mkdtemp(bad) || !mkdtemp(empty)) {
        perror("mkdtemp");
        return 1;
    }
    CHECK(write_file(good, good_names[0], trigger_link_tsv) == 0);
    CHECK(write_file(good, good_names[1], features_tsv) == 0);
    CHECK(write_file(good, good_names[2], status_tsv) == 0);
    CHECK(write_file(good, good_names[3], dvs_words_tsv) == 0);
    vr_run_dir(&c, good);
    printf("hand-made vectors: %d passed, %d failed\n", c.passed, c.failed);
    CHECK(c.passed == 14 && c.failed == 0);

    c.passed = c.failed = 0;
    fprintf(stderr, "--- the failures below are expected ---\n");
    CHECK(write_file(bad, bad_names[0], wrong_tsv) == 0);
    CHECK(write_file(bad, bad_names[1], "valid\tx\t00\tx\n") == 0);
    vr_run_dir(&c, bad);
    printf("wrong vectors: %d passed, %d failed\n", c.passed, c.failed);
    CHECK(c.passed == 0 && c.failed == 7);

    c.passed = c.failed = 0;
    vr_run_dir(&c, empty);
    CHECK(c.passed == 0 && c.failed == 0);
    fprintf(stderr, "--- end of expected failures ---\n");

    remove_dir(good, good_names, 4);
    remove_dir(bad, bad_names, 2);
    rmdir(empty);
    return ft_test_report("test_vector_runner");
}
