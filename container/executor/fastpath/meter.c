#include "fastpath.h"

/* Meter: what one entity's callbacks cost, per window (see
 * container/executor/_accounting.py for the figures built on it).
 *
 * Why here: every path that runs a callback (the async chain, the Python
 * lanes' first steps and later steps, the worker threads' plain calls) is
 * timed at the same two points, with the GIL held, so a meter needs no lock
 * of its own and a step costs two CLOCK_MONOTONIC reads (about 22 ns each
 * here) and a few additions.
 *
 * CPU time: the thread's own CPU clock is a system call (about 520 ns on
 * this project's VM, against 14 us for a whole ping-pong round trip), so a
 * thread reads it only at the end of a step that lasted CPU_READ_NS or more,
 * and at the start of a step when CPU_READ_PERIOD_NS has passed since its
 * last read (what it spent since then was spent outside steps). Other steps
 * are credited their wall time. A step that ends with a read gets what the
 * thread really spent since the last read, less what the steps in between
 * were credited, at most its wall time and at least zero: a plain callback
 * that sleeps is credited the CPU it used, give or take what its thread spent
 * outside steps in the CPU_READ_PERIOD_NS before it. Short steps, the bulk of
 * any busy process, cost no system call. What a thread spends outside steps
 * (waiting, taking, dispatching) is nobody's callback: the executor's own
 * share.
 *
 * Lateness is from when the work arrived (a message taken, a timer's due
 * time) to its first step's start; duration from that start to the end of
 * its last step (an async callback's awaits included). Both go into
 * log-linear histograms (METER_SUB buckets per power of two, about 9% wide)
 * that take() turns into p50, p99 and max and clears.
 *
 * Stuck: a step running for stuck_after_ns or more (a plain callback
 * blocked on its worker, an async one holding the loop). Counted once per
 * step, by take() while it lasts or at its end. */

/* A step this long or longer ends with a read of its thread's CPU clock. */
#define CPU_READ_NS 1000000LL
/* A step starts with one when the thread's last read is this old. */
#define CPU_READ_PERIOD_NS 10000000LL

static long long stuck_after_ns = 1000000000LL;

static THREAD_LOCAL long long cpu_read_at;  /* monotonic ns of this thread's last CPU read */
static THREAD_LOCAL long long cpu_at_read;  /* its CPU clock then */
static THREAD_LOCAL long long cpu_credited; /* wall time credited to steps since */

static inline long long thread_cpu_ns(void)
{
  struct timespec now;
  if (clock_gettime(CLOCK_THREAD_CPUTIME_ID, &now) != 0) {
    return 0;
  }
  return (long long)now.tv_sec * 1000000000LL + now.tv_nsec;
}

static inline int bucket_of(long long value)
{
  int exponent, index;
  if (value < METER_SUB) {
    return value < 0 ? 0 : (int)value;
  }
  exponent = 63 - __builtin_clzll((unsigned long long)value);
  index = (exponent - 2) * METER_SUB + (int)((value >> (exponent - 3)) & (METER_SUB - 1));
  return index < METER_BUCKETS ? index : METER_BUCKETS - 1;
}

/* The middle of bucket ``index``'s range. */
static inline long long bucket_value(int index)
{
  long long exponent, low, width;
  if (index < METER_SUB) {
    return index;
  }
  exponent = index / METER_SUB + 2;
  width = 1LL << (exponent - 3);
  low = (1LL << exponent) + (long long)(index % METER_SUB) * width;
  return low + width / 2;
}

static inline void record(uint32_t * histogram, unsigned long long * count, long long * max, long long value)
{
  if (value < 0) {
    value = 0;
  }
  histogram[bucket_of(value)]++;
  (*count)++;
  if (value > *max) {
    *max = value;
  }
}

/* The value at quantile q (0..1) of a histogram of count values, at most max. */
static long long quantile(const uint32_t * histogram, unsigned long long count, long long max, double q)
{
  unsigned long long rank, seen = 0;
  int i;
  long long value;
  if (count == 0) {
    return 0;
  }
  rank = (unsigned long long)(q * (double)(count - 1)) + 1;
  for (i = 0; i < METER_BUCKETS; ++i) {
    seen += histogram[i];
    if (seen >= rank) {
      value = bucket_value(i);
      return value < max ? value : max;
    }
  }
  return max;
}

static inline void step_in(MeterObject * self, long long now)
{
  if (now - cpu_read_at >= CPU_READ_PERIOD_NS) {
    /* What the thread spent since its last read was spent outside steps. */
    cpu_at_read = thread_cpu_ns();
    cpu_read_at = now;
    cpu_credited = 0;
  }
  if (self->in_step++ == 0) {
    self->step_since = now;
    self->stuck_counted = 0;
  }
}

long long meter_begin(MeterObject * self, long long arrived)
{
  long long now = monotonic_ns();
  self->runs++;
  if (arrived > 0) {
    record(self->late, &self->late_n, &self->late_max, now - arrived);
  }
  step_in(self, now);
  return now;
}

long long meter_resume(MeterObject * self)
{
  long long now = monotonic_ns();
  step_in(self, now);
  return now;
}

static long long step_out(MeterObject * self, long long step_start)
{
  long long now = monotonic_ns();
  long long wall = now - step_start, spent;
  if (wall < 0) {
    wall = 0;
  }
  self->busy_ns += wall;
  if (wall >= CPU_READ_NS) {
    long long cpu = thread_cpu_ns();
    spent = cpu - cpu_at_read - cpu_credited;
    spent = spent < 0 ? 0 : (spent > wall ? wall : spent);
    cpu_read_at = now;
    cpu_at_read = cpu;
    cpu_credited = 0;
  } else {
    spent = wall;
    cpu_credited += wall;
  }
  self->cpu_ns += spent;
  if (wall >= stuck_after_ns && !self->stuck_counted) {
    self->stuck++;
    self->stuck_counted = 1;
  }
  if (self->in_step > 0) {
    self->in_step--;
  }
  return now;
}

void meter_pause(MeterObject * self, long long step_start)
{
  step_out(self, step_start);
}

void meter_end(MeterObject * self, long long step_start, long long started)
{
  long long now = step_out(self, step_start);
  self->finished++;
  record(self->dur, &self->dur_n, &self->dur_max, now - started);
}

/* What take() gives for a window in which nothing ran: made once, then shared (the module holds it). */
static PyObject * idle_figures = NULL;

/* take() -> tuple: this window's figures, then a new window.
 *
 * A window in which nothing ran, and nothing runs, is the same zeros every
 * time, and most meters' windows are so (a node's parameter services): 500
 * nodes' 7,500 meters, each window built and cleared anew, were most of a
 * sample's 26 ms, once a second. */
static PyObject * Meter_take(MeterObject * self, PyObject * Py_UNUSED(ignored))
{
  long long now = monotonic_ns();
  long long running = self->in_step > 0 ? now - self->step_since : 0;
  PyObject * figures;
  if (self->in_step == 0 && self->runs == 0 && self->finished == 0 && self->busy_ns == 0 && self->cpu_ns == 0 &&
      self->late_n == 0 && self->dur_n == 0 && self->dropped == 0 && self->stuck == 0)
  {
    if (idle_figures == NULL) {
      idle_figures = Py_BuildValue("(iiiiiiiiiiiii)", 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0);
      if (idle_figures == NULL) {
        return NULL;
      }
    }
    return Py_NewRef(idle_figures);
  }
  if (running >= stuck_after_ns && !self->stuck_counted) {
    self->stuck++;
    self->stuck_counted = 1;
  }
  figures = Py_BuildValue(
    "(KKLLLLLLLLKKL)", self->runs, self->finished, self->busy_ns, self->cpu_ns,
    quantile(self->late, self->late_n, self->late_max, 0.5), quantile(self->late, self->late_n, self->late_max, 0.99),
    self->late_max, quantile(self->dur, self->dur_n, self->dur_max, 0.5),
    quantile(self->dur, self->dur_n, self->dur_max, 0.99), self->dur_max, self->dropped, self->stuck, running);
  if (figures == NULL) {
    return NULL;
  }
  self->runs = self->finished = self->dropped = self->stuck = 0;
  self->busy_ns = self->cpu_ns = self->late_max = self->dur_max = 0;
  self->late_n = self->dur_n = 0;
  memset(self->late, 0, sizeof(self->late));
  memset(self->dur, 0, sizeof(self->dur));
  return figures;
}

/* call(arrived, call, *args) -> object: call(*args) as one run of this meter, begun
 * (its lateness from arrived; 0: unknown) and ended when it returns or raises.
 *
 * Why here: the event loop's own callbacks (a reader, a call_later handle)
 * that a node scheduled are timed as its callbacks are, with the same two
 * clock reads and without a Work per call (see container/executor/_loop.py). */
static PyObject * Meter_call(MeterObject * self, PyObject * const * args, Py_ssize_t nargs)
{
  long long arrived, start;
  PyObject * result;
  if (nargs < 2) {
    PyErr_SetString(PyExc_TypeError, "call(arrived, call, *args)");
    return NULL;
  }
  arrived = PyLong_AsLongLong(args[0]);
  if (arrived == -1 && PyErr_Occurred()) {
    return NULL;
  }
  start = meter_begin(self, arrived);
  Py_INCREF(self); /* the call may drop the last other reference to this meter */
  result = PyObject_Vectorcall(args[1], args + 2, (size_t)(nargs - 2), NULL);
  meter_end(self, start, start);
  Py_DECREF(self);
  return result;
}

static PyMethodDef Meter_methods[] = {
  {"call", (PyCFunction)(void (*)(void))Meter_call, METH_FASTCALL,
   "call(arrived, call, *args) -> object: call(*args) as one run of this meter (arrived: monotonic ns, 0 unknown)"},
  {"take", (PyCFunction)Meter_take, METH_NOARGS,
   "take() -> (runs, finished, busy_ns, cpu_ns, late_p50, late_p99, late_max, duration_p50, duration_p99, "
   "duration_max, dropped, stuck, running_ns): this window's figures (ns), then a new window"},
  {NULL, NULL, 0, NULL},
};

/* running -> int: how long the step running now has run (ns; 0: none runs). Read by the
 * watchdog's thread to name which node's loop work holds the loop (container/executor/_loop.py). */
static PyObject * Meter_get_running(MeterObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromLongLong(self->in_step > 0 ? monotonic_ns() - self->step_since : 0);
}

static PyGetSetDef Meter_getset[] = {
  {"running", (getter)Meter_get_running, NULL, "How long the step running now has run (ns; 0: none runs).", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

PyTypeObject MeterType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Meter",
  .tp_doc = "Meter(): what one entity's callbacks cost, per window (runs, CPU, lateness, duration, drops, stuck).",
  .tp_basicsize = sizeof(MeterObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_methods = Meter_methods,
  .tp_getset = Meter_getset,
};

/* stuck_after(ns) -> None: how long a step runs before it counts as stuck (all meters). */
static PyObject * meters_stuck_after(PyObject * Py_UNUSED(module), PyObject * arg)
{
  long long ns = PyLong_AsLongLong(arg);
  if (ns == -1 && PyErr_Occurred()) {
    return NULL;
  }
  if (ns <= 0) {
    PyErr_SetString(PyExc_ValueError, "stuck_after: a positive number of nanoseconds");
    return NULL;
  }
  stuck_after_ns = ns;
  Py_RETURN_NONE;
}

PyMethodDef meter_functions[] = {
  {"stuck_after", meters_stuck_after, METH_O,
   "stuck_after(ns) -> None: how long one step of a callback runs before its meter counts it stuck"},
  {NULL, NULL, 0, NULL},
};
