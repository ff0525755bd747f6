/* Handoff: the busy loop thread lets go of the GIL until the worker it just woke has it.
 *
 * A plain callback runs on its lane's worker thread, which needs the GIL.
 * While the loop's thread is busy (an asyncio task publishing in a loop),
 * it never sleeps, so the worker gets the GIL only when CPython forces a
 * switch (sys.getswitchinterval(), 5 ms), and every voluntary release by
 * the loop (a zero-timeout poll) restarts that wait: beside a busy async
 * publisher of 1080p images, a plain subscriber got 4 of the 3,900 frames a
 * second an async one got. Here the loop thread, before its next asyncio
 * iteration, waits (without the GIL) until each worker it handed work to
 * since has started (took the GIL and its work), bounded by a timeout.
 *
 * It waits for the start, not the end: a callback that blocks lets the
 * GIL go and the loop runs on at once; one that computes holds the loop
 * for one switch interval, as any thread holding the GIL does. Isolation
 * is what it was. After the start it only stays awake, spinning without
 * the GIL and briefly, for those workers to finish (see give()): on a
 * virtual machine, letting its core go idle costs more than a short
 * callback.
 *
 * Every spin here (give's, a worker's linger, the loop's linger) is for
 * a thread running on another CPU at the same time. With one CPU for the
 * process the awaited thread needs this thread's CPU to make progress,
 * so spinning only delays it: the executor then makes its Handoff with
 * spin=False (_dispatch.py, from _cores.usable_cpus(), counted once when
 * the executor is made), and none of them spins. The wait for the
 * workers' starts stays: it sleeps on a condition variable, which is what
 * hands the one CPU and the GIL to the worker.
 *
 * The spin and linger bounds below were measured on the project's 2-core
 * shared KVM virtual machine only, with the benchmarks named at each; none
 * has been measured with one CPU or with more than two.
 */
#include "fastpath.h"

#include <errno.h>
#include <sched.h>
#include <stdatomic.h>
#include <time.h>

struct HandoffObject {
  PyObject_HEAD
  pthread_mutex_t mutex;
  pthread_cond_t started_cond;
  long outstanding; /* handed and not yet started; under mutex */
  atomic_long running; /* started (by a hand-over) and not finished */
  int waiting;      /* the loop thread waits in give(); under mutex */
  unsigned long long given; /* gives that waited (for tests and benchmarks) */
  atomic_ulong handed_total; /* hand-overs ever: what a lingering worker watches */
  atomic_long inflight;      /* handed and not finished: what the lingering loop watches */
  atomic_int loop_free;      /* the loop thread is in a wait without the GIL */
  int spin;                  /* whether a thread may stay awake for another (set once: see Handoff_new) */
  int misses;                /* the loop's lingers in a row that saw no answer (loop thread only) */
  int skip;                  /* lingers the loop skips after misses (loop thread only) */
  int backoff;               /* how many the next misses make it skip (loop thread only) */
  unsigned long long lingered; /* the loop's lingers that saw the answer (tests, benchmarks) */
};

/* Handoff(*, spin=True). Without spin (one CPU for the process: spinning
 * there only keeps the awaited thread off the CPU), give() waits for the
 * workers' starts without staying awake for their ends, a worker never
 * lingers and the loop never stays awake for an answer. */
static PyObject * Handoff_new(PyTypeObject * type, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"spin", NULL};
  HandoffObject * self;
  pthread_condattr_t attr;
  int spin = 1;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "|$p:Handoff", keywords, &spin)) {
    return NULL;
  }
  self = (HandoffObject *)type->tp_alloc(type, 0);
  if (self == NULL) {
    return NULL;
  }
  self->spin = spin;
  pthread_mutex_init(&self->mutex, NULL);
  pthread_condattr_init(&attr);
  pthread_condattr_setclock(&attr, CLOCK_MONOTONIC);
  pthread_cond_init(&self->started_cond, &attr);
  pthread_condattr_destroy(&attr);
  return (PyObject *)self;
}

static void Handoff_dealloc(HandoffObject * self)
{
  pthread_cond_destroy(&self->started_cond);
  pthread_mutex_destroy(&self->mutex);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * Handoff_handed(HandoffObject * self, PyObject * Py_UNUSED(ignored))
{
  pthread_mutex_lock(&self->mutex);
  self->outstanding++;
  pthread_mutex_unlock(&self->mutex);
  atomic_fetch_add(&self->inflight, 1);
  atomic_fetch_add(&self->handed_total, 1);
  Py_RETURN_NONE;
}

static PyObject * Handoff_started(HandoffObject * self, PyObject * Py_UNUSED(ignored))
{
  atomic_fetch_add(&self->running, 1);
  pthread_mutex_lock(&self->mutex);
  if (self->outstanding > 0) {
    self->outstanding--;
  }
  if (self->outstanding == 0 && self->waiting) {
    pthread_cond_signal(&self->started_cond);
  }
  pthread_mutex_unlock(&self->mutex);
  Py_RETURN_NONE;
}

static PyObject * Handoff_finished(HandoffObject * self, PyObject * Py_UNUSED(ignored))
{
  if (atomic_load(&self->running) > 0) {
    atomic_fetch_sub(&self->running, 1);
  }
  if (atomic_load(&self->inflight) > 0) {
    atomic_fetch_sub(&self->inflight, 1);
  }
  Py_RETURN_NONE;
}

static PyObject * Handoff_give(HandoffObject * self, PyObject * args)
{
  long long timeout_ns;
  long long spin_ns = 0;
  struct timespec deadline;
  int waited = 0;
  long before;
  if (!PyArg_ParseTuple(args, "L|L:give", &timeout_ns, &spin_ns)) {
    return NULL;
  }
  if (timeout_ns < 0) {
    timeout_ns = 0; /* a deadline in the past: a negative tv_nsec would make the wait fail at once, forever */
  }
  /* Workers running before this give's own start: not waited for (one
   * blocking for seconds in another group would cost every give the spin). */
  before = atomic_load(&self->running);
  pthread_mutex_lock(&self->mutex);
  if (self->outstanding == 0) {
    pthread_mutex_unlock(&self->mutex);
    Py_RETURN_FALSE;
  }
  pthread_mutex_unlock(&self->mutex);
  clock_gettime(CLOCK_MONOTONIC, &deadline);
  deadline.tv_sec += (time_t)(timeout_ns / 1000000000LL);
  deadline.tv_nsec += (long)(timeout_ns % 1000000000LL);
  if (deadline.tv_nsec >= 1000000000L) {
    deadline.tv_sec++;
    deadline.tv_nsec -= 1000000000L;
  }
  Py_BEGIN_ALLOW_THREADS
  atomic_store(&self->loop_free, 1);
  pthread_mutex_lock(&self->mutex);
  self->waiting = 1;
  while (self->outstanding > 0) {
    waited = 1;
    if (pthread_cond_timedwait(&self->started_cond, &self->mutex, &deadline) == ETIMEDOUT) {
      break;
    }
  }
  /* Not started in time (a worker starting up, a starved core): forget
   * them, or the next give would wait for them again. */
  self->outstanding = 0;
  self->waiting = 0;
  pthread_mutex_unlock(&self->mutex);
  if (waited && spin_ns > 0 && self->spin) {
    /* A short callback is done within microseconds: staying awake for it
     * keeps this thread's core from going idle, and on a virtual machine
     * waking an idle core costs 50-200 us, twice per hand-over (the GIL
     * comes back through a condition variable too). One that runs longer
     * is left to the GIL as before. Never on one CPU (spin=False): the
     * worker could only finish once this thread gave the CPU back. */
    long long until = monotonic_ns() + spin_ns;
    while (atomic_load(&self->running) > before && monotonic_ns() < until) {
      sched_yield();
    }
  }
  atomic_store(&self->loop_free, 0);
  Py_END_ALLOW_THREADS
  if (waited) {
    self->given++;
  }
  return PyBool_FromLong(waited);
}

/* linger(spin_ns) -> bool, on a worker thread that just finished its work.
 *
 * Plain work handed over at a high rate (a plain service answering calls
 * one after another) finds its worker asleep every time, and on a virtual
 * machine the wake-up of an idle core costs more than the call (measured:
 * plain service calls ran 7,500 a second, and 11,300-12,800 with two
 * idle-priority busy loops keeping both cores awake). So a worker whose work
 * has been coming quickly stays awake, without the GIL, for up to spin_ns:
 * until the loop hands work over again and has let go of the GIL (or 50 us
 * after the hand-over, should it hold on to the GIL). The caller decides
 * whether lingering pays (how long it waited last time).
 *
 * LINGER_GIL_GRACE_NS (50 us), here and in handoff_loop_linger: came with
 * the lingers (commit bc7e731) and was measured only as part of them, on
 * the 2-core shared KVM VM: plain service calls 7,430-7,614/s before,
 * 19,770-20,200/s after (bench_executor.py --only services --kinds
 * asyncio-plain single --rounds 4 --seconds 3, the code before side by
 * side; see LOOP_LINGER_NS); no other value of it was measured. On one
 * CPU it is never reached: nothing lingers (spin=False). */
#define LINGER_GIL_GRACE_NS 50000LL
static PyObject * Handoff_linger(HandoffObject * self, PyObject * arg)
{
  long long spin_ns = PyLong_AsLongLong(arg);
  unsigned long seen;
  int handed = 0;
  if (spin_ns == -1 && PyErr_Occurred()) {
    return NULL;
  }
  if (!self->spin) {
    Py_RETURN_FALSE;
  }
  seen = atomic_load(&self->handed_total);
  Py_BEGIN_ALLOW_THREADS
  long long now = monotonic_ns();
  long long until = now + spin_ns;
  long long handed_at = 0;
  while (now < until) {
    if (!handed && atomic_load(&self->handed_total) != seen) {
      handed = 1;
      handed_at = now;
    }
    if (handed && (atomic_load(&self->loop_free) || now - handed_at >= LINGER_GIL_GRACE_NS)) {
      break;
    }
    sched_yield();
    now = monotonic_ns();
  }
  Py_END_ALLOW_THREADS
  return PyBool_FromLong(handed);
}

/* How long the loop thread stays awake for an answer from the workers it
 * woke. After LOOP_MISSES_MAX lingers in a row that saw none (plain timers,
 * whose callbacks answer nothing; a callback blocking for long), the next
 * waits block at once: LOOP_SKIP of them, twice as many after each such
 * round up to LOOP_SKIP_MAX, back to LOOP_SKIP once a linger sees an answer.
 * A callback blocked for good costs two lingers per LOOP_SKIP_MAX waits.
 *
 * Measured against (commit bc7e731, on the 2-core shared KVM VM, the
 * code before side by side through bench_executor.py --pythons): the four
 * together with the worker's linger (_workers.py WORKER_LINGER_NS) took
 * plain service calls from 7,430-7,614/s to 19,770-20,200/s (--only
 * services --kinds asyncio-plain single --rounds 4 --seconds 3); the same
 * comparison of the ten-node load (--only load: the backoff is for plain
 * timers, whose callbacks answer nothing) gave 1.01x the CPU with plain
 * callbacks, ping-pong 0.98x, the gap unchanged. Why staying awake pays
 * there: with two idle-priority busy loops keeping both cores awake, the
 * same plain service calls ran 11,300-12,800/s instead of 7,500
 * (docs/design.md, Services). The values themselves (250 us; 2 misses;
 * 32, doubling to 4,096 skips) were not measured against others: no such
 * measurement is recorded. On one CPU the loop never lingers
 * (handoff_may_linger: spin=False), so none of them applies. */
#define LOOP_LINGER_NS 250000LL
#define LOOP_MISSES_MAX 2
#define LOOP_SKIP 32
#define LOOP_SKIP_MAX 4096

int handoff_may_linger(HandoffObject * self)
{
  if (!self->spin || atomic_load(&self->inflight) <= 0) {
    return 0;
  }
  if (self->skip > 0) {
    self->skip--;
    return 0;
  }
  return 1;
}

/* A linger of the loop's saw its answer: lingering pays again. */
static int answered(HandoffObject * self)
{
  self->misses = 0;
  self->backoff = LOOP_SKIP;
  self->lingered++;
  return 1;
}

int handoff_loop_linger(HandoffObject * self, const atomic_int * armed, long long timeout_ns)
{
  long long now, until, limit = LOOP_LINGER_NS;
  if (timeout_ns >= 0 && timeout_ns < limit) {
    limit = timeout_ns;
  }
  long long answered_at = 0;
  now = monotonic_ns();
  until = now + limit;
  while (now < until) {
    if (!atomic_load(armed)) {
      /* The answer is in (it woke the notifier; a publish a worker takes
       * itself does not): a moment more for its worker to let go of the
       * GIL (not for others still running: one may block for seconds). */
      if (answered_at == 0) {
        answered_at = now;
      }
      if (atomic_load(&self->inflight) <= 0 || now - answered_at >= LINGER_GIL_GRACE_NS) {
        return answered(self);
      }
    } else if (atomic_load(&self->inflight) <= 0) {
      break; /* done without an answer for this thread */
    }
    sched_yield();
    now = monotonic_ns();
  }
  if (!atomic_load(armed)) {
    return answered(self);
  }
  /* No answer: the work was a plain timer's, or runs long. Staying awake
   * was for nothing; after a few such, block at once for a while. */
  if (++self->misses >= LOOP_MISSES_MAX) {
    self->misses = 0;
    self->skip = self->backoff > LOOP_SKIP ? self->backoff : LOOP_SKIP;
    self->backoff = self->skip < LOOP_SKIP_MAX / 2 ? self->skip * 2 : LOOP_SKIP_MAX;
  }
  return 0;
}

void handoff_loop_free(HandoffObject * self, int free)
{
  atomic_store(&self->loop_free, free);
}

static PyObject * Handoff_get_lingered(HandoffObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromUnsignedLongLong(self->lingered);
}

static PyObject * Handoff_get_outstanding(HandoffObject * self, void * Py_UNUSED(closure))
{
  long outstanding;
  pthread_mutex_lock(&self->mutex);
  outstanding = self->outstanding;
  pthread_mutex_unlock(&self->mutex);
  return PyLong_FromLong(outstanding);
}

static PyObject * Handoff_get_given(HandoffObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromUnsignedLongLong(self->given);
}

static PyObject * Handoff_get_spin(HandoffObject * self, void * Py_UNUSED(closure))
{
  return PyBool_FromLong(self->spin);
}

static PyMethodDef Handoff_methods[] = {
  {"handed", (PyCFunction)Handoff_handed, METH_NOARGS,
   "handed(): the loop thread just woke a worker with plain work."},
  {"started", (PyCFunction)Handoff_started, METH_NOARGS,
   "started(): a worker woken by handed() holds the GIL and its work."},
  {"finished", (PyCFunction)Handoff_finished, METH_NOARGS,
   "finished(): a worker that started() is done and about to wait for work again."},
  {"give", (PyCFunction)Handoff_give, METH_VARARGS,
   "give(timeout_ns, spin_ns=0) -> bool: without the GIL, wait until every handed worker started "
   "(at most timeout_ns), then stay awake until they finished (at most spin_ns); "
   "False at once when none is outstanding."},
  {"linger", (PyCFunction)Handoff_linger, METH_O,
   "linger(spin_ns) -> bool: on a worker, stay awake without the GIL until work is handed over "
   "again and the loop let go of the GIL (at most spin_ns); whether work was handed over."},
  {NULL, NULL, 0, NULL},
};

static PyGetSetDef Handoff_getset[] = {
  {"outstanding", (getter)Handoff_get_outstanding, NULL, "Workers handed work and not started yet.", NULL},
  {"given", (getter)Handoff_get_given, NULL, "How often give() let the GIL go.", NULL},
  {"lingered", (getter)Handoff_get_lingered, NULL, "The loop's waits that stayed awake and saw the answer.", NULL},
  {"spin", (getter)Handoff_get_spin, NULL, "Whether a thread may stay awake (spinning) for another's hand-over.", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

PyTypeObject HandoffType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Handoff",
  .tp_doc = "The busy loop thread lets go of the GIL until the workers it woke have started.",
  .tp_basicsize = sizeof(HandoffObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = Handoff_new,
  .tp_dealloc = (destructor)Handoff_dealloc,
  .tp_methods = Handoff_methods,
  .tp_getset = Handoff_getset,
};
