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
 */
#include "fastpath.h"

#include <errno.h>
#include <sched.h>
#include <stdatomic.h>
#include <time.h>

typedef struct {
  PyObject_HEAD
  pthread_mutex_t mutex;
  pthread_cond_t started_cond;
  long outstanding; /* handed and not yet started; under mutex */
  atomic_long running; /* started (by a hand-over) and not finished */
  int waiting;      /* the loop thread waits in give(); under mutex */
  unsigned long long given; /* gives that waited (for tests and benchmarks) */
} HandoffObject;

static PyObject * Handoff_new(PyTypeObject * type, PyObject * args, PyObject * kwargs)
{
  HandoffObject * self;
  pthread_condattr_t attr;
  if ((args != NULL && PyTuple_GET_SIZE(args) != 0) || (kwargs != NULL && PyDict_GET_SIZE(kwargs) != 0)) {
    PyErr_SetString(PyExc_TypeError, "Handoff() takes no arguments");
    return NULL;
  }
  self = (HandoffObject *)type->tp_alloc(type, 0);
  if (self == NULL) {
    return NULL;
  }
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
  Py_RETURN_NONE;
}

static long long now_ns(void)
{
  struct timespec now;
  clock_gettime(CLOCK_MONOTONIC, &now);
  return (long long)now.tv_sec * 1000000000LL + now.tv_nsec;
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
  if (waited && spin_ns > 0) {
    /* A short callback is done within microseconds: staying awake for it
     * keeps this thread's core from going idle, and on a virtual machine
     * waking an idle core costs 50-200 us, twice per hand-over (the GIL
     * comes back through a condition variable too). One that runs longer
     * is left to the GIL as before. */
    long long until = now_ns() + spin_ns;
    while (atomic_load(&self->running) > before && now_ns() < until) {
      sched_yield();
    }
  }
  Py_END_ALLOW_THREADS
  if (waited) {
    self->given++;
  }
  return PyBool_FromLong(waited);
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
  {NULL, NULL, 0, NULL},
};

static PyGetSetDef Handoff_getset[] = {
  {"outstanding", (getter)Handoff_get_outstanding, NULL, "Workers handed work and not started yet.", NULL},
  {"given", (getter)Handoff_get_given, NULL, "How often give() let the GIL go.", NULL},
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
