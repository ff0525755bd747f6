#include "fastpath.h"

/* Lock: a mutex the Python side uses as threading.Lock (``with``, acquire,
 * release, locked) and this module checks and takes without a Python call.
 *
 * Why: the wait set's take lock is taken once per batch of the async chain
 * and a lane's lock is looked at twice per callback; through threading.Lock
 * that is a bound-method call each, whose argument parsing alone cost about
 * 2% of a ping-pong (measured with perf on 3.12). ``locked`` is kept in the
 * object: every acquire and release happens with the GIL held (a blocked
 * acquire lets the GIL go only while it waits), so the field is exact for
 * any thread holding the GIL. */
static PyObject * Lock_new(PyTypeObject * type, PyObject * args, PyObject * kwargs)
{
  LockObject * self;
  if ((args != NULL && PyTuple_GET_SIZE(args) != 0) || (kwargs != NULL && PyDict_GET_SIZE(kwargs) != 0)) {
    PyErr_SetString(PyExc_TypeError, "Lock() takes no arguments");
    return NULL;
  }
  self = (LockObject *)type->tp_alloc(type, 0);
  if (self == NULL) {
    return NULL;
  }
  self->lock = PyThread_allocate_lock();
  if (self->lock == NULL) {
    Py_DECREF(self);
    return PyErr_NoMemory();
  }
  return (PyObject *)self;
}

static void Lock_dealloc(LockObject * self)
{
  if (self->lock != NULL) {
    if (self->locked) {
      PyThread_release_lock(self->lock);
    }
    PyThread_free_lock(self->lock);
  }
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * Lock_acquire(LockObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"blocking", "timeout", NULL};
  int blocking = 1;
  double timeout = -1.0;
  PY_TIMEOUT_T microseconds;
  long long deadline;
  PyLockStatus status;
  if ((args != NULL || kwargs != NULL) &&
      !PyArg_ParseTupleAndKeywords(args, kwargs, "|pd:acquire", keywords, &blocking, &timeout)) {
    return NULL;
  }
  if (!blocking && timeout != -1.0) {
    PyErr_SetString(PyExc_ValueError, "can't specify a timeout for a non-blocking call");
    return NULL;
  }
  if (!(timeout >= 0) && timeout != -1.0) { /* NaN too */
    PyErr_SetString(PyExc_ValueError, "timeout value must be a non-negative number");
    return NULL;
  }
  if (lock_try(self)) {
    Py_RETURN_TRUE;
  }
  if (!blocking) {
    Py_RETURN_FALSE;
  }
  if (timeout > (double)PY_TIMEOUT_MAX / 1e6) {
    PyErr_SetString(PyExc_OverflowError, "timeout value is too large");
    return NULL;
  }
  microseconds = timeout < 0 ? -1 : (PY_TIMEOUT_T)(timeout * 1e6);
  /* As threading.Lock's: a signal interrupts the wait, its handler runs
   * (Ctrl-C raises there), and the wait goes on for what is left. */
  deadline = 0;
  if (microseconds > 0) {
    long long now = monotonic_ns();
    deadline = microseconds > (LLONG_MAX - now) / 1000LL ? LLONG_MAX : now + microseconds * 1000LL;
  }
  for (;;) {
    Py_BEGIN_ALLOW_THREADS
    status = PyThread_acquire_lock_timed(self->lock, microseconds, 1);
    Py_END_ALLOW_THREADS
    if (status != PY_LOCK_INTR) {
      break;
    }
    if (Py_MakePendingCalls() < 0) {
      return NULL;
    }
    if (microseconds > 0) {
      microseconds = (deadline - monotonic_ns()) / 1000LL;
      if (microseconds <= 0) {
        status = PY_LOCK_FAILURE;
        break;
      }
    }
  }
  if (status != PY_LOCK_ACQUIRED) {
    Py_RETURN_FALSE;
  }
  self->locked = 1;
  Py_RETURN_TRUE;
}

static PyObject * Lock_enter(LockObject * self, PyObject * Py_UNUSED(ignored))
{
  return Lock_acquire(self, NULL, NULL);
}

static PyObject * Lock_release(LockObject * self, PyObject * Py_UNUSED(ignored))
{
  if (!self->locked) {
    PyErr_SetString(PyExc_RuntimeError, "release unlocked lock");
    return NULL;
  }
  lock_release(self);
  Py_RETURN_NONE;
}

static PyObject * Lock_exit(LockObject * self, PyObject * Py_UNUSED(args))
{
  return Lock_release(self, NULL);
}

static PyObject * Lock_locked(LockObject * self, PyObject * Py_UNUSED(ignored))
{
  return PyBool_FromLong(self->locked);
}

static PyMethodDef Lock_methods[] = {
  {"acquire", (PyCFunction)(void (*)(void))Lock_acquire, METH_VARARGS | METH_KEYWORDS,
   "acquire(blocking=True, timeout=-1) -> bool, as threading.Lock's"},
  {"release", (PyCFunction)Lock_release, METH_NOARGS, "release() -> None"},
  {"locked", (PyCFunction)Lock_locked, METH_NOARGS, "locked() -> bool"},
  {"__enter__", (PyCFunction)Lock_enter, METH_NOARGS, NULL},
  {"__exit__", (PyCFunction)Lock_exit, METH_VARARGS, NULL},
  {NULL, NULL, 0, NULL},
};

PyTypeObject LockType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Lock",
  .tp_doc = "A mutex used as threading.Lock, which the compiled path checks and takes directly.",
  .tp_basicsize = sizeof(LockObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = Lock_new,
  .tp_dealloc = (destructor)Lock_dealloc,
  .tp_methods = Lock_methods,
};

