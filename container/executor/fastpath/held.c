/* held.c: what a compiled object owns of rclpy's: handles, and message types' functions.
 *
 * Why: an rcl pointer is valid only while the rclpy handle that owns it has
 * not destroyed it, and rclpy destroys it when asked (node.destroy_*(),
 * shutdown) unless the handle is entered: then destruction waits for the
 * last exit (rclpy's Destroyable, and its events executor's ScopedWith).
 * So every compiled object that reads a pointer holds and enters the handle
 * it came from, for as long as it may read it, and reads the pointer from
 * the handle itself. Likewise a message type's conversion functions are read
 * from its capsules, which the object holds.
 */
#include "fastpath.h"

int held_enter(Held * held, PyObject * handle)
{
  PyObject * result, * pointer;
  void * address;
  held->handle = NULL;
  held->pointer = NULL;
  if (handle == NULL || handle == Py_None || PyLong_Check(handle)) {
    PyErr_Format(
      PyExc_TypeError, "an rclpy handle is needed (the entity's .handle), not %.100s",
      handle == NULL ? "nothing" : Py_TYPE(handle)->tp_name);
    return -1;
  }
  /* Entered first: a handle destroyed already raises rclpy's InvalidHandle here. */
  result = PyObject_CallMethod(handle, "__enter__", NULL);
  if (result == NULL) {
    return -1;
  }
  Py_DECREF(result);
  held->handle = Py_NewRef(handle);
  pointer = PyObject_GetAttrString(handle, "pointer");
  address = pointer != NULL ? PyLong_AsVoidPtr(pointer) : NULL;
  Py_XDECREF(pointer);
  if (address == NULL) {
    if (!PyErr_Occurred()) {
      PyErr_Format(PyExc_ValueError, "%.200s has no rcl object (pointer 0)", Py_TYPE(handle)->tp_name);
    }
    held_exit(held);
    return -1;
  }
  held->pointer = address;
  return 0;
}

void held_exit(Held * held)
{
  PyObject * handle = held->handle, * result, * type, * value, * traceback;
  if (handle == NULL) {
    return;
  }
  held->handle = NULL;
  held->pointer = NULL;
  PyErr_Fetch(&type, &value, &traceback);
  result = PyObject_CallMethod(handle, "__exit__", "OOO", Py_None, Py_None, Py_None);
  if (result == NULL) {
    PyErr_WriteUnraisable(handle);
  }
  Py_XDECREF(result);
  Py_DECREF(handle);
  PyErr_Restore(type, value, traceback);
}

int held_enter_all(PyObject * sequence, Held ** out, size_t * count)
{
  PyObject * fast = PySequence_Fast(sequence, "entities must be a sequence of rclpy handles");
  Py_ssize_t i, n;
  *out = NULL;
  *count = 0;
  if (fast == NULL) {
    return -1;
  }
  n = PySequence_Fast_GET_SIZE(fast);
  *out = calloc(n > 0 ? (size_t)n : 1, sizeof(Held));
  if (*out == NULL) {
    Py_DECREF(fast);
    PyErr_NoMemory();
    return -1;
  }
  for (i = 0; i < n; ++i) {
    if (held_enter(&(*out)[i], PySequence_Fast_GET_ITEM(fast, i)) < 0) {
      *count = (size_t)i;
      held_exit_all(out, count);
      Py_DECREF(fast);
      return -1;
    }
  }
  *count = (size_t)n;
  Py_DECREF(fast);
  return 0;
}

void held_exit_all(Held ** held, size_t * count)
{
  size_t i;
  if (*held == NULL) {
    return;
  }
  for (i = *count; i > 0; --i) {
    held_exit(&(*held)[i - 1]);
  }
  free(*held);
  *held = NULL;
  *count = 0;
}

/* The pointer in capsule attribute ``name`` of ``type``, the capsule appended to ``capsules``. */
static void * capsule_pointer(PyObject * type, const char * name, PyObject * capsules)
{
  void * pointer;
  PyObject * capsule = PyObject_GetAttrString(type, name);
  if (capsule == NULL) {
    return NULL;
  }
  pointer = PyCapsule_GetPointer(capsule, NULL);
  if (pointer != NULL && PyList_Append(capsules, capsule) < 0) {
    pointer = NULL;
  }
  Py_DECREF(capsule);
  return pointer;
}

int message_functions(PyObject * type, const char * part, int want_from_py, MessageFunctions * out)
{
  PyObject * message_type = part != NULL ? PyObject_GetAttrString(type, part) : Py_NewRef(type);
  PyObject * capsules;
  memset(out, 0, sizeof(*out));
  if (message_type == NULL) {
    return -1;
  }
  capsules = PyList_New(0);
  if (capsules == NULL) {
    Py_DECREF(message_type);
    return -1;
  }
  out->create = (create_message_t)capsule_pointer(message_type, "_CREATE_ROS_MESSAGE", capsules);
  out->destroy = out->create != NULL ? (destroy_message_t)capsule_pointer(message_type, "_DESTROY_ROS_MESSAGE", capsules) : NULL;
  out->to_py = out->destroy != NULL ? (convert_to_py_t)capsule_pointer(message_type, "_CONVERT_TO_PY", capsules) : NULL;
  if (out->to_py != NULL && want_from_py) {
    out->from_py = (bool (*)(PyObject *, void *))capsule_pointer(message_type, "_CONVERT_FROM_PY", capsules);
  }
  if (out->to_py == NULL || (want_from_py && out->from_py == NULL)) {
    Py_DECREF(capsules);
    Py_DECREF(message_type);
    memset(out, 0, sizeof(*out));
    return -1;
  }
  out->type = message_type;
  out->capsules = PyList_AsTuple(capsules);
  Py_DECREF(capsules);
  if (out->capsules == NULL) {
    message_functions_clear(out);
    return -1;
  }
  return 0;
}

void message_functions_clear(MessageFunctions * functions)
{
  Py_CLEAR(functions->type);
  Py_CLEAR(functions->capsules);
  functions->create = NULL;
  functions->destroy = NULL;
  functions->to_py = NULL;
  functions->from_py = NULL;
}
